"""Settings of the executor: fixed skill parameters, the safety envelope, timeouts (AERMANI_EXECUTOR_*)."""

from __future__ import annotations

from pydantic import model_validator
from pydantic_settings import SettingsConfigDict

from shared import envelope
from shared.settings import ServiceSettings


class ExecutorSettings(ServiceSettings):
    """Executor configuration (AERMANI_EXECUTOR_*): skill modules, flight and manipulation parameters, timeouts."""

    model_config = SettingsConfigDict(env_prefix="AERMANI_EXECUTOR_", extra="ignore", populate_by_name=True,
                                      use_attribute_docstrings=True)

    skill_modules: list[str] = []
    """Python modules to import at start-up that register extra skills (`@register` from
    services.executor.registry), e.g. `["my_lab.skills.inspect"]`: a skill is one module plus its
    registration; the prompt, the validator and the rules baseline read it from the served library."""

    memory_restore: bool = False
    """Accept `executor/restore_memory` (a recorded working memory put back for a task that continues a recorded
    one). Off by default: on a vehicle nobody should replace what the executor has seen; `aermani fork` and
    `aermani eval --fork-from` turn it on in the simulated stack they start."""

    # ---- motion primitives (fixed parameters, paper Table II)
    yaw_step_deg: float = 45.0
    """Rotation of yaw_left / yaw_right, degrees. 45 keeps consecutive views of the 85 deg camera
    overlapping while a full scan takes 8 steps instead of 12."""
    horizontal_step: float = 0.5
    """Translation of forward / backward / left / right, metres."""
    vertical_step: float = 0.3
    """Translation of up / down, metres."""
    translation_speed: float = 0.5
    """Speed of motion primitives, m/s."""
    approach_speed: float = 0.6
    """Speed of grasp/place approach legs, m/s."""
    descent_speed: float = 0.25
    """Speed of the controlled descent and ascent of grasp and place, m/s."""

    # ---- safety envelope
    geofence_min: tuple[float, float, float] = envelope.GEOFENCE_MIN
    """Geofence box lower corner (world ENU x, y, z), metres. Every target and the vehicle stay inside."""
    geofence_max: tuple[float, float, float] = envelope.GEOFENCE_MAX
    """Geofence box upper corner (world ENU x, y, z), metres."""
    min_altitude: float = envelope.MIN_ALTITUDE
    """Lowest altitude of motion primitives and transit legs, metres."""
    max_altitude: float = envelope.MAX_ALTITUDE
    """Highest altitude allowed, metres."""
    manipulation_min_altitude: float = envelope.MANIPULATION_MIN_ALTITUDE
    """Lowest body altitude of the grasp/place descent (the gripper hangs 0.22 m below), metres."""
    max_speed: float = envelope.MAX_SPEED
    """Speed limit sent with every setpoint, m/s; a measured speed above max_speed + overspeed_margin aborts."""
    overspeed_margin: float = 0.6
    """Tolerance above max_speed before the monitor declares an overspeed, m/s."""
    overspeed_persist_s: float = 1.2
    """How long an overspeed must last before the skill fails. Longer than PX4's 1 Hz HEARTBEAT, so when a PX4
    failsafe (RTL climbs at several m/s) is the cause, the takeover is reported first and the skill ends with
    PX4's reason instead of commanding a hold that would fight it."""
    state_max_age_s: float = 0.5
    """Vehicle state older than this is stale: no motion starts, a running skill holds and fails."""
    geofence_exit_margin: float = 0.2
    """The monitor stops a skill when the vehicle is this far outside the geofence, metres."""
    clearance_margin: float = 0.3
    """Extra free distance required beyond a forward step, metres."""
    clearance_half_width: float = 0.35
    """Half-width of the swept corridor checked in the depth image (airframe radius + margin), metres."""
    clearance_above: float = 0.2
    """Corridor extends this far above the body origin, metres."""
    clearance_below: float = 0.35
    """Corridor extends this far below the body origin (gripper and a held object), metres."""
    clearance_min_points: int = 30
    """Depth points inside the corridor needed to call it an obstacle (rejects speckle)."""
    depth_max_age_s: float = 1.0
    """Depth image older than this cannot vouch for forward clearance."""

    # ---- termination
    position_tolerance: float = 0.08
    """Arrival: distance to the target, metres."""
    yaw_tolerance_deg: float = 5.0
    """Arrival: heading error, degrees."""
    settle_speed: float = 0.15
    """Arrival: speed below this, m/s."""
    motion_slack_s: float = 8.0
    """Added to the nominal duration of a motion for its timeout, seconds."""
    takeoff_timeout_s: float = 60.0
    """Timeout of takeoff, seconds."""
    land_timeout_s: float = 60.0
    """Timeout of land, seconds."""
    localize_timeout_s: float = 10.0
    """Timeout of a perception query, seconds."""
    grasp_timeout_s: float = 240.0
    """Timeout of the whole grasp routine, seconds."""
    place_timeout_s: float = 120.0
    """Timeout of the whole place routine, seconds."""
    fresh_frame_timeout_s: float = 3.0
    """How long a localization waits for a camera frame captured after the vehicle settled, seconds."""
    command_timeout_s: float = 5.0
    """Timeout of an autopilot command reply (takeoff excepted), seconds."""
    gripper_timeout_s: float = 4.0
    """Time for the gripper to follow a command (its state, then both pads on the object or an empty close, then
    the pads off it), seconds. A small servo gripper closes at 0.15 m/s (services/sim/README.md "Gripper"): the
    full 18 cm in 1.2 s, the narrowest object (a 2.5 cm screwdriver) held after 1.0 s, the holding flag at 10 Hz
    through the bridge; 4 s leaves 3x that for a simulator running slower than real time under load (the 12 N
    gripper this was 3 s for closed in ~0.15 s)."""

    # ---- routines
    flight_altitude: float = 1.5
    """Takeoff and transit altitude; grasp and place retreat to it, metres."""
    standoff_distance: float = 0.75
    """Horizontal distance from the object at which grasp/place re-localize, facing it, metres."""
    reach: float = 2.0
    """Grasp starts only for an object within this horizontal distance, metres; beyond it the skill is
    rejected with "too far: approach first". Bounded by grasp's first re-look from the standoff (the object must
    be re-found within max_object_shift of memory): the measured error curve of the realistic depth camera
    (benchmarks/depth_error.py) plus the estimate's drift keeps that within budget up to 3 m; docs/skills.md."""
    place_reach: float = 6.0
    """Place starts only for a placement spot within this horizontal distance, metres (not yet from a measured
    curve: the placement estimate is re-used as is, and the rules baseline approaches a surface by where it
    saw it, not by the spot)."""
    camera_min_depth: float = 0.2
    """Nearest depth the RGB-D camera measures, metres (the simulator's stereo model: services/sim/render.py
    MIN_DEPTH_M): grasp's last view of an object keeps its near top edge beyond it."""
    gripper_max_opening: float = 0.18
    """Widest opening of the gripper's fingers, metres: objects wider across their narrow side are refused."""
    final_descent_speed: float = 0.1
    """Speed of the last part of the descent onto an object, m/s (closing while descending fast fails)."""
    localization_max_age_s: float = 120.0
    """A grasp needs a localization of the object younger than this, seconds (memory is in world frame)."""
    relocalize_iterations: int = 3
    """Maximum re-localizations at the standoff during grasp."""
    relocalize_converged: float = 0.05
    """Re-localization stops when the estimate moves less than this, metres."""
    max_object_shift: float = 0.3
    """An object re-localized farther than this from memory has moved: grasp fails, re-localize first."""
    grasp_depth_fraction: float = 0.4
    """Gripper point target below the object's top, as a fraction of its height (grip_depth: never so deep
    that the landing gear's feet reach the surface it stands on). Near the middle: the pads (6 cm tall, their
    centre 5 mm above the gripper point) cover a sphere's equator with 1.7 cm to spare below it, and a tall
    object hangs from near its centre of mass. At 0.25 the pads' lower edge sat 5 mm under an 8 cm fruit's
    equator and, a centimetre high, squeezed it out downwards (dev grasp benchmark: apples and oranges slipped
    on the lift), and a bottle held by its top 8 cm fell from the pads in transit (dev seed 5)."""
    place_vertical_offset: float = 0.03
    """Release height of the object's bottom above the surface, metres."""
    verify_tolerance: float = 0.12
    """A localization within this of the pre-grasp position means the object was not picked, metres."""
    place_tolerance: float = 0.2
    """After place, the object must be seen within this of the placement spot, metres."""
    grasp_attempts: int = 3
    """Closed-loop grasp attempts per call (each failed one leaves its reason in the outcome's facts)."""
    pregrasp_backoff: float = 0.35
    """Pre-grasp pose: the gripper point this far behind the object along the approach (body x) axis, where the
    forward camera still sees the object (right above it, it cannot), metres."""
    pregrasp_height: float = 0.12
    """Pre-grasp pose: the gripper point this far above the object's top, metres."""
    hover_clearance: float = 0.03
    """After a failed attempt the finger pads climb this far above the object's top before backing off to look
    at it again (clear of whatever the attempt left standing or lying between them), metres."""
    grasp_window_x: float = 0.018
    """Closing is allowed only with the gripper point within this of the object along the pad width (body x;
    the pads are 5 cm wide: +-2.5 cm lifts), metres."""
    grasp_window_y: float = 0.03
    """... and within this along the closing axis (body y; +-5 cm lifts a cup), metres."""
    align_samples: int = 5
    """Consecutive state samples (50 Hz) inside the window before the gripper closes: a wandering vehicle is
    caught while it is aligned, not on one lucky sample."""
    close_lead_s: float = 0.4
    """The close also waits until the gripper point, carried this long at the present velocity, is inside the
    window: the pads reach a fruit 0.67 s after the close is commanded (0.15 m/s from 18 cm open), and the hover
    keeps wandering meanwhile; an object closed on more than the pad's half-width (2.5 cm) off its centre is held
    on the pad's edge, and a fruit held there falls out in transit. In-process on the realistic multirotor
    (benchmarks/close_timing.py, noise seeds 0-59, 900 closes per lead): closing in a steady hover on an object
    known exactly at the start of the wait, 5.6 % of the closes left it beyond the edge without the lead and 3.1 %
    with 0.4 s; with the estimate's drift over a 1.6 s blind leg since the last detection counted (what the grasp
    meets), 23.0 % and 20.7 %: the drift, not the close's timing, is most of the error. Seconds; 0 turns it off."""
    align_corrections: int = 4
    """Setpoint corrections (by the measured mean offset) before an alignment gives up as misaligned."""
    align_timeout_s: float = 2.0
    """Time to wait for an aligned window after each correction, seconds."""
    track_converged: float = 0.012
    """Close-range re-localization: two consecutive detections closer than this agree, metres."""
    knock_shift: float = 0.06
    """After a failed close, an object re-detected this far from where it stood was pushed by the attempt, metres:
    still standing, the next attempt starts from where it stands now (noted); lower or lying on its side in two
    looks it was knocked over, whatever the shift, and the grasp ends knocked_over (as the simulator's judge
    counts a knock: tipped, or on another support). Nearer, it did not move: on a hovering multirotor two
    detections from beside the object scatter by up to ~5 cm."""
    chord_tolerance: float = 0.008
    """A round object held this much narrower than it measures is gripped off-centre, on a chord (the pads
    reach past its middle along their width) and slips when lifted: the gripper reopens and retries, metres."""
    catalog_chord_tolerance: float = 0.002
    """A round object (in perception's catalogue: a cup, a can, a bottle, a fruit) held this much narrower than its
    catalogued diameter is held on the pads' edge, off their centre along their width by more than half of it, and
    the gripper reopens and retries (the check above, against the width perception measured, misses what is within
    perception's error of a centimetre). Dev grasp run at c42cc26 (realistic, seeds 0-23): the three objects that
    fell from the pads in transit were held 0.3-1.8 cm narrower (a coke can and a soda can at 6.3 cm, a purple cup
    at 6.2), every hold that survived within 0.1 cm of the catalogue (cups 7.9-8.0, cans 6.7, bottle 7.0-7.1) but
    one orange at 6.9; the simulator's gap reading is exact, a real servo's a millimetre or two. Metres."""
    hold_width_tolerance: float = 0.035
    """A closed gripper whose finger gap differs from the object's measured width by more than this holds
    something else, metres."""
    rest_tolerance: float = 0.025
    """After place, two detections of the released object 0.5 s apart closer than this horizontally mean it is
    at rest, metres. Horizontally only, and not tighter: the vehicle's estimate wanders between the looks (on the
    realistic multirotor two looks at a resting cup 0.5 s apart differ by a median 0.9 cm, at most 1.9 cm,
    horizontally, and by 1.5 cm in 3-D, where the vertical wander dominates), while an object still rolling or
    sliding after the retreat moves 2.5 cm in 0.5 s at 5 cm/s."""
    support_tolerance: float = 0.03
    """After place, the support seen under the object and the named surface's top, both from the verification
    view, agree within this, metres."""
    estimate_wander_z: float = 0.05
    """How far the vehicle's vertical position estimate may wander between two views seconds apart, added to
    support_tolerance when the surface's top can only be compared with its measurement from before the release:
    about 2 sigma of the change of the realistic multirotor's vertical estimate error (sigma 2.8 cm, tau 10 s),
    metres. On a real vehicle, from its estimator's specification."""
    upright_tolerance: float = 0.03
    """After place, a non-rolling object seen this much (or a quarter of its height, whichever is more) shorter
    than it was held has fallen over, metres."""
    round_place_margin: float = 0.12
    """Extra clearance from the surface's edges for a round (rolling) object's placement spot, metres."""

    memory_period_s: float = 1.0
    """Working memory is republished at this period besides every change, seconds."""

    @model_validator(mode="after")
    def _sane(self) -> ExecutorSettings:
        # Refuse unsafe combinations instead of flying them.
        envelope.check_settings(self)
        if self.max_altitude > self.geofence_max[2]:
            raise ValueError("max_altitude is above the geofence ceiling")
        if not self.min_altitude <= self.flight_altitude <= self.max_altitude:
            raise ValueError("flight_altitude must lie in the altitude band")
        for name in ("translation_speed", "approach_speed", "descent_speed"):
            if not 0 < getattr(self, name) <= self.max_speed:
                raise ValueError(f"{name} must be in (0, max_speed]")
        return self

    @property
    def gripper_offset_z(self) -> float:
        """Gripper capture point below the body origin, metres (from the one mount definition, `mount`)."""
        return float(self.mount.gripper_offset[2])

    @property
    def camera_pitch_deg(self) -> float:
        """Camera pitch below the horizon, degrees: sets the standoff height that keeps a target in view."""
        return float(self.mount.camera_pitch_deg)
