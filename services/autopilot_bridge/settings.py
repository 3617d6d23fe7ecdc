"""Settings of the autopilot bridge (env prefix AERMANI_AUTOPILOT_BRIDGE_)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from shared.settings import ServiceSettings


class BridgeSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AERMANI_AUTOPILOT_BRIDGE_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    connection: str = "udpin:0.0.0.0:14540"
    """MAVLink link: udpin:0.0.0.0:14540 for PX4 SITL's offboard link (also udpout:, udp:, tcp:), or
    serial:/dev/ttyACM0:921600 (device and optional baud; /dev/serial/by-id/... paths work) for hardware."""
    baud: int = Field(921600, gt=0)
    """Serial baud rate when the connection names none (ignored for UDP)."""
    target_system: int = Field(0, ge=0, le=255)
    """PX4 system id to talk to; 0 = learn it from the first PX4 HEARTBEAT (others are then ignored)."""
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
    max_speed: float = Field(3.0, gt=0.0)
    """Upper bound of a goto's max_speed ramp, m/s."""
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
    publish_tf: bool = False
    """Publish tf world->base_link from LOCAL_POSITION_NED/ATTITUDE. Off by default because the simulator
    publishes tf itself; turn it on for real hardware and PX4 SITL."""
    health_period_s: float = Field(1.0, gt=0.0)
    """Period of health/autopilot_bridge."""
    gil_switch_interval_s: float = Field(0.0005, gt=0.0, le=0.01)
    """Python thread switch interval for this process; small so the setpoint thread gets the GIL quickly."""
    stream_realtime_priority: int = Field(10, ge=0, le=99)
    """SCHED_FIFO priority of the setpoint thread when the OS allows it (root or CAP_SYS_NICE); 0 = never."""

    @field_validator("connection")
    @classmethod
    def _connection(cls, v: str) -> str:
        from services.autopilot_bridge.link import parse_connection  # noqa: PLC0415 (pymavlink import cost)

        try:
            parse_connection(v)
        except Exception as exc:
            raise ValueError(str(exc)) from exc
        return v.strip()
