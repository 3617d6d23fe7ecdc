"""Settings of the built-in simulator (env AERMANI_SIM_*)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator
from pydantic_settings import NoDecode, SettingsConfigDict

from services.sim.layout import DEFAULT_DYNAMICS
from shared.settings import ServiceSettings, parse_endpoints


class SimSettings(ServiceSettings):
    """Simulator configuration (AERMANI_SIM_*): scenario seed and target, realism, rates and camera."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_SIM_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    seed: int = 0
    """Layout seed of the initial scenario."""
    target_object: str | None = None
    """Target object of the initial scenario (e.g. "red cup"); empty lets the seed choose."""
    destination: str | None = None
    """Destination surface of the initial scenario (e.g. "table"); empty lets the seed choose."""
    distractors: Annotated[list[str] | None, NoDecode] = None
    """Distractor objects (comma-separated); empty lets the seed choose."""
    extra_objects: Annotated[list[str], NoDecode] = []
    """Objects that must be present besides target and distractors (comma-separated)."""
    target_out_of_view: bool = False
    """Place the target outside the initial camera view."""

    restore: str | None = None
    """A recorded simulator state to start from instead of the initial scenario: a file holding one `sim/state`
    sample (JSON, as `aermani fork` writes it). The room is rebuilt from the scenario it was generated from and
    everything else is restored: objects, the vehicle in the air (in Hold where it flew), the gripper and what it
    holds, the estimator's and the disturbances' random states. Empty: the initial scenario."""
    restore_seed: int | None = Field(None, ge=0)
    """With `restore`: draw the vehicle's noise (estimator error, air, thrust) and the camera's afresh from this seed
    instead of continuing the recorded draws: the same moment with another realisation of the noise (`aermani eval
    --fork-from` runs its second and later forks so). Empty: the recorded draws continue."""
    snapshots: bool = True
    """Publish the whole state on `sim/state` whenever a skill ends (about 12 kB each): the points a recorded
    flight can be forked at (`aermani fork LOG --step K`)."""

    camera: bool = True
    """Publish the simulated camera (colour, depth, segmentation, calibration) and tf. Off when a camera service
    owns those keys (drone-side tests, `aermani up` with AERMANI_CAMERA_SOURCE set): the simulator then only
    flies over MAVLink, and the autopilot bridge must publish world->base_link (AERMANI_AUTOPILOT_BRIDGE_PUBLISH_TF)."""
    fps: float = Field(15.0, gt=0, le=60)
    """Camera frame rate (colour, depth, segmentation and tf), frames per second."""
    jpeg_quality: int = Field(85, ge=10, le=100)
    """JPEG quality of the colour frames."""
    render_scale: int = Field(1, ge=1, le=4)
    """Render at 1/render_scale of the resolution and upsample (1 = full resolution)."""
    realism: Literal["realistic", "ideal", "harsh"] = "realistic"
    """realistic: a stereo depth camera's flaws (noise, scale bias, occlusion bands, flying pixels, dropouts,
    colour/depth misregistration, frame latency), exposure and lighting variation, textured objects and a
    drifting VIO-like pose estimate; with dynamics=multirotor also indoor air (draft, turbulence, gusts), thrust
    noise, ground effect and downwash (hover error sigma 2-5 cm). harsh: the same camera flaws, worse; with
    dynamics=multirotor stronger wind and gusts and a worse estimate (stress tests). ideal: clean buffers,
    primitive shapes, still air and the true pose (debugging). services/sim/README.md (Realism)."""
    camera_unit: int = Field(0, ge=0)
    """The simulated camera unit: its depth scale bias and colour/depth misregistration are drawn from it (a
    unit's calibration error, the same in every run), services/sim/README.md (Realism)."""
    camera_latency_s: float | None = Field(None, ge=0, le=1.0)
    """Delay from a frame's capture to its publication, seconds; frames keep the capture stamp and tf is not
    delayed. Empty: the realism level's (ideal 0, realistic 0.07, harsh 0.15)."""
    dynamics: Literal["kinematic", "multirotor"] = DEFAULT_DYNAMICS
    """The vehicle's body. kinematic: an ideal body on sliding joints pushed by a perfect world-frame force (it
    never tilts; position error in hover a few mm). multirotor: a free rigid body with four lagged rotors flown by
    a PX4-style cascade (position/velocity, attitude, rate, mixer), which tilts to accelerate and carries the
    disturbances of the realism level (services/sim/README.md "Dynamics")."""
    render_always: bool = False
    """Render even when nobody subscribes to the camera keys (by default idle frames publish tf only)."""
    render_process: bool = True
    """Render in a child process (rendering and the camera model would compete with MAVLink for the GIL)."""

    api_host: str = "127.0.0.1"
    """Host the offboard/API link sends to (where the autopilot bridge listens)."""
    api_port: int = Field(14540, ge=1, le=65535)
    """UDP port the offboard/API link sends to (PX4 SITL: 14540)."""
    api_local_port: int = Field(14580, ge=1, le=65535)
    """Local UDP port of the offboard/API link (PX4 SITL: 14580)."""
    gcs_enabled: bool = True
    """Also open the ground-station link."""
    gcs_host: str = "127.0.0.1"
    """Host the ground-station link sends to."""
    gcs_port: int = Field(14550, ge=1, le=65535)
    """UDP port the ground-station link sends to (QGroundControl: 14550)."""
    gcs_local_port: int = Field(18570, ge=1, le=65535)
    """Local UDP port of the ground-station link (PX4 SITL: 18570)."""
    bind_host: str = "127.0.0.1"
    """Address the MAVLink sockets bind to (0.0.0.0 to accept other machines)."""

    speed_factor: float = Field(1.0, gt=0, le=20)
    """Simulated time runs this many times faster than wall time (dynamics only)."""
    physics_rate: float = Field(200.0, ge=100, le=1000)
    """Physics and MAVLink loop rate, Hz."""
    offboard_loss_timeout: float = Field(0.5, gt=0)
    """COM_OF_LOSS_T: seconds without setpoints in OFFBOARD before the failsafe holds."""
    failsafe_land_delay: float = Field(3.0, ge=0)
    """COM_FAIL_ACT_T: seconds of failsafe hold before an action beyond Hold (COM_OBL_RC_ACT=4 lands after it)."""
    takeoff_alt: float = Field(1.5, gt=0)
    """MIS_TAKEOFF_ALT: default take-off altitude above home, metres."""
    hover_offset: Annotated[tuple[float, float], NoDecode] = (0.0, 0.0)
    """Where the vehicle settles relative to an OFFBOARD position setpoint (world x, y), metres, e.g. `0.04,0.03`:
    a steady error the vehicle's own estimate shows (wind, a mistrimmed controller). For tests of closed-loop
    skills; 0,0 flies to the setpoint."""
    px4_params: Annotated[dict[str, float], NoDecode] = Field(default_factory=dict)
    """PX4 parameters the simulated autopilot starts with instead of its defaults, `NAME=value,...`: e.g.
    `COM_OBL_RC_ACT=4` lands in place on offboard loss (the default 5 holds), `COM_OBL_RC_ACT=7,GF_ACTION=0` is an
    airframe configured unsafely, which the bridge's preflight must refuse. Only the failsafe names of
    services.sim.mavlink_server.FAILSAFE_PARAMS: COM_OBL_RC_ACT and COM_FAIL_ACT_T are flown (over
    failsafe_land_delay), the geofence ones only reported."""

    @field_validator("distractors", "extra_objects", mode="before")
    @classmethod
    def _names(cls, v: object) -> object:
        if isinstance(v, str):
            return parse_endpoints(v) if v.strip() else None
        return v

    @field_validator("px4_params", mode="before")
    @classmethod
    def _params(cls, v: object) -> object:
        if not isinstance(v, str):
            return v
        from services.sim.mavlink_server import FAILSAFE_PARAMS

        out: dict[str, float] = {}
        for item in (x.strip() for x in v.split(",")):
            if not item:
                continue
            name, sep, value = item.partition("=")
            if not sep or name.strip() not in FAILSAFE_PARAMS:
                raise ValueError(f"{item!r}: expected NAME=value with NAME one of {', '.join(FAILSAFE_PARAMS)}")
            out[name.strip()] = float(value)
        return out

    @field_validator("hover_offset", mode="before")
    @classmethod
    def _pair(cls, v: object) -> object:
        if isinstance(v, str):
            parts = [x for x in v.replace(",", " ").split() if x]
            if len(parts) != 2:
                raise ValueError(f"expected two numbers x,y (metres), got {v!r}")
            return tuple(float(x) for x in parts)
        return v

    @field_validator("target_object", "destination", "restore", "restore_seed", mode="before")
    @classmethod
    def _empty(cls, v: object) -> object:
        return None if isinstance(v, str) and not v.strip() else v
