"""Settings of the autopilot bridge (env prefix AERMANI_AUTOPILOT_BRIDGE_)."""

from __future__ import annotations

from typing import Literal

from pydantic import AliasChoices, Field, SecretStr, field_validator, model_validator
from pydantic_settings import SettingsConfigDict

from shared import envelope
from shared.errors import ConfigError
from shared.settings import ServiceSettings


def _env(field: str, executor_field: str | None = None) -> AliasChoices:
    """The bridge's own variable first, then the executor's: one setting moves both fences."""
    return AliasChoices(field, f"AERMANI_AUTOPILOT_BRIDGE_{field.upper()}",
                        f"AERMANI_EXECUTOR_{(executor_field or field).upper()}")


class BridgeSettings(ServiceSettings):
    """Autopilot bridge configuration (AERMANI_AUTOPILOT_BRIDGE_*): MAVLink link, geofence, limits, gripper."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_AUTOPILOT_BRIDGE_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    connection: str = "udpin:127.0.0.1:14540"
    """MAVLink link: udpin:127.0.0.1:14540 for PX4 SITL's offboard link on this host (also udpout:, udp:, tcp:),
    or serial:/dev/ttyACM0:921600 (device and optional baud; /dev/serial/by-id/... paths work) for hardware.
    Loopback by default: whoever reaches this port first is taken for the autopilot, so listen on another
    interface (udpin:0.0.0.0:...) only inside a network namespace that nothing else reaches (compose)."""
    baud: int = Field(921600, gt=0)
    """Serial baud rate when the connection names none (ignored for UDP)."""
    target_system: int = Field(1, ge=1, le=255)
    """The autopilot's MAVLink system id (PX4's MAV_SYS_ID, 1 by default). Only a PX4 HEARTBEAT from this system
    and `target_component` is taken for the autopilot; every other system on the link (another vehicle, a fake
    autopilot) is ignored, and one that claims to be an autopilot is logged once with its address."""
    target_component: int = Field(1, ge=1, le=255)
    """The autopilot's MAVLink component id (1 = MAV_COMP_ID_AUTOPILOT1, PX4's own). Messages from other
    components of the same system (a camera, a gimbal) never become the vehicle's state."""
    signing_key: SecretStr | None = None
    """MAVLink 2 signing key shared with the autopilot: 64 hex digits (32 bytes), from the environment only,
    never logged. Set: every frame the bridge sends is signed, and only frames signed with this key are heard
    (unsigned, MAVLink 1 and wrongly signed ones are counted and dropped). Unset (the default): no signing, as
    PX4 without a key on its SD card. docs/px4-sitl.md, "MAVLink 2 signing"."""
    source_system: int = Field(1, ge=1, le=255)
    """Our MAVLink system id. MAVLink's routing guide puts a companion computer in its autopilot's system (PX4's
    MAV_SYS_ID, 1 by default) under its own component id; 255 belongs to ground stations, so is not the default."""
    source_component: int = Field(191, ge=1, le=255)
    """Our MAVLink component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER; 192-194 for further companions)."""
    heartbeat_timeout_s: float = Field(2.0, gt=0.0)
    """No autopilot HEARTBEAT for this long means the link is lost."""
    stream_rate_hz: float = Field(20.0, ge=2.0, le=100.0)
    """Offboard setpoint stream rate; PX4 needs > 2 Hz, 20 Hz is the norm."""
    offboard_warmup_s: float = Field(1.1, ge=0.0)
    """How long the setpoint stream runs before we ask for OFFBOARD (PX4 wants > 1 s)."""
    state_rate_hz: float = Field(30.0, ge=1.0, le=100.0)
    """Rate of autopilot/state (and tf when enabled)."""
    telemetry_rate_hz: float = Field(50.0, gt=0.0, le=250.0)
    """Rate requested from PX4 for LOCAL_POSITION_NED and ATTITUDE."""
    takeoff_timeout_s: float = Field(40.0, gt=0.0)
    """Takeoff fails when the altitude is not reached within this time."""
    arrival_tolerance_m: float = Field(0.1, gt=0.0)
    """Takeoff counts as done within this distance of the target altitude."""
    # ---- the envelope, checked on every command whoever sent it (shared/envelope.py)
    geofence_min: tuple[float, float, float] = Field(envelope.GEOFENCE_MIN, validation_alias=_env("geofence_min"))
    """Geofence box lower corner (world ENU), metres; a goto or takeoff target outside is refused.
    Also read from AERMANI_EXECUTOR_GEOFENCE_MIN."""
    geofence_max: tuple[float, float, float] = Field(envelope.GEOFENCE_MAX, validation_alias=_env("geofence_max"))
    """Geofence box upper corner, metres (also AERMANI_EXECUTOR_GEOFENCE_MAX)."""
    min_altitude: float = Field(envelope.MANIPULATION_MIN_ALTITUDE,
                                validation_alias=_env("min_altitude", "manipulation_min_altitude"))
    """Lowest goto/takeoff target altitude, metres: the executor's grasp/place floor (also
    AERMANI_EXECUTOR_MANIPULATION_MIN_ALTITUDE). Landing goes through `land`, not goto."""
    max_altitude: float = Field(envelope.MAX_ALTITUDE, validation_alias=_env("max_altitude"))
    """Highest goto/takeoff target altitude, metres (also AERMANI_EXECUTOR_MAX_ALTITUDE)."""
    max_speed: float = Field(envelope.MAX_SPEED, gt=0.0, validation_alias=_env("max_speed"))
    """Speed limit of a goto, m/s (also AERMANI_EXECUTOR_MAX_SPEED): a faster max_speed is refused and a goto
    without one is ramped at this speed."""
    command_timeout_s: float = Field(1.5, gt=0.0)
    """Time to wait for a COMMAND_ACK before resending (MAVLink command protocol)."""
    command_attempts: int = Field(3, ge=1, le=10)
    """Sends of one COMMAND_LONG before giving up."""
    mode_timeout_s: float = Field(3.0, gt=0.0)
    """After an accepted mode change, time to see the new mode in HEARTBEAT."""
    abort_hold: Literal["offboard", "px4_hold"] = "offboard"
    """How the bridge holds on safety/abort (also when the executor is dead): `offboard` freezes its own setpoint
    stream at the current position (PX4 holds there; a new task continues from the air), `px4_hold` switches
    PX4 to AUTO.LOITER and stops the stream (holds even if the bridge dies next; a new task must land and take
    off again, or an operator re-enters OFFBOARD by hand)."""
    gripper_id: int = Field(1, ge=1, le=6)
    """Gripper instance for MAV_CMD_DO_GRIPPER param 1."""
    gripper_actuation: Literal["gripper", "actuator"] = "gripper"
    """How the gripper is driven: `gripper` = MAV_CMD_DO_GRIPPER (PX4's payload deliverer, PD_GRIPPER_EN=1);
    `actuator` = MAV_CMD_DO_SET_ACTUATOR on output function "Peripheral via Actuator Set N" (a servo on any
    PWM/AUX output; N = gripper_actuator_index)."""
    gripper_actuator_index: int = Field(1, ge=1, le=6)
    """N of "Peripheral via Actuator Set N" (DO_SET_ACTUATOR param N) for gripper_actuation=actuator."""
    gripper_actuator_open: float = Field(-1.0, ge=-1.0, le=1.0)
    """Actuator value (-1..1) that opens the gripper."""
    gripper_actuator_closed: float = Field(1.0, ge=-1.0, le=1.0)
    """Actuator value (-1..1) that closes the gripper."""
    preflight_override: bool = False
    """Arm even when the preflight fails (PX4's failsafe parameters, link, estimate, battery); every such arm is
    logged with the failed checks. For a bench or a simulator set up on purpose, never for a flight."""
    preflight_override_reason: str = Field("", max_length=200)
    """Why the override is on (recorded with every overridden verdict on autopilot/preflight)."""
    preflight_min_battery: float = Field(30.0, ge=0.0, le=100.0)
    """Preflight refuses to arm below this battery charge (percent, when PX4 reports one)."""
    publish_tf: bool | Literal["auto"] = False
    """Publish tf world->base_link from LOCAL_POSITION_NED/ATTITUDE. Off by default because the simulator
    publishes tf itself; on for real hardware and PX4 SITL. `auto` (compose's drone profile): on, except while
    the vehicle's simulator says in its health that it publishes the camera and tf (the `sim` profile), so one
    drone profile serves a real vehicle and the simulator without two world->base_link publishers. It decides
    after AUTO_TF_GRACE_S from start (the simulator's health comes at 1 Hz)."""
    health_period_s: float = Field(1.0, gt=0.0)
    """Period of health/autopilot_bridge."""
    gil_switch_interval_s: float = Field(0.0005, gt=0.0, le=0.01)
    """Python thread switch interval for this process; small so the setpoint thread gets the GIL quickly."""
    stream_realtime_priority: int = Field(10, ge=0, le=99)
    """SCHED_FIFO priority of the setpoint thread when the OS allows it (root or CAP_SYS_NICE); 0 = never."""

    @model_validator(mode="after")
    def _check_envelope(self) -> BridgeSettings:
        envelope.check_settings(self)
        return self

    @field_validator("signing_key")
    @classmethod
    def _signing_key(cls, v: SecretStr | None) -> SecretStr | None:
        if v is None or not v.get_secret_value().strip():
            return None  # unset, or empty as compose passes an unset variable
        try:
            ok = len(bytes.fromhex(v.get_secret_value().strip())) == 32
        except ValueError:
            ok = False
        if not ok:  # ConfigError, not ValueError: pydantic would repeat the key in its error's input_value
            raise ConfigError("AERMANI_AUTOPILOT_BRIDGE_SIGNING_KEY must be 64 hex digits (32 bytes), e.g. from "
                              "`openssl rand -hex 32`")
        return SecretStr(v.get_secret_value().strip().lower())

    @property
    def signing_key_bytes(self) -> bytes | None:
        return bytes.fromhex(self.signing_key.get_secret_value()) if self.signing_key is not None else None

    @field_validator("connection")
    @classmethod
    def _connection(cls, v: str) -> str:
        from services.autopilot_bridge.link import parse_connection  # noqa: PLC0415 (pymavlink import cost)

        try:
            parse_connection(v)
        except Exception as exc:
            raise ValueError(str(exc)) from exc
        return v.strip()
