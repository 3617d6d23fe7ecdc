"""Manipulation routines (paper Table III): grasp and place."""

from __future__ import annotations

import contextlib
import math
from typing import ClassVar

from services.executor.context import SkillContext, SkillFailed
from services.executor.envelope import geofence_problem, wrap
from services.executor.memory import age_s, horizontal_distance
from services.executor.registry import Category, Skill, SkillResult, register
from services.executor.skills.common import beyond_reach, fmt, not_found
from shared import skills as names
from shared.messages import (
    GripperState,
    MemoryObject,
    ObjectEstimate,
    SkillParameter,
    Vec3,
    VehicleState,
)

GRASP_SETTLE_M = 0.02  # the body must be this close to the grasp point before the gripper closes
GRASP_SETTLE_TIMEOUT_S = 3.0  # ... or close anyway after this (the verification then tells)
FINAL_DESCENT_M = 0.10  # the last part of the descent onto an object runs at final_descent_speed
PAD_BELOW_M = 0.03  # the finger pads reach this far below the gripper point (plus a few mm of margin)
ROUND_TOLERANCE_M = 0.015  # footprint sides closer than this: a round object, any yaw grasps it


def grip_depth(height: float, fraction: float) -> float:
    """How far below an object's top the gripper point goes: a fraction of its height, but the pads must stay
    above the surface it stands on (a flat wrench is gripped near its middle, pads just above the table)."""
    return max(0.0, min(fraction * height, height - PAD_BELOW_M))


def grasp_yaw(size: Vec3 | None, est_yaw: float, current_yaw: float) -> float:
    """Vehicle yaw that closes the fingers (along the body's y axis) across the object's short side: body x
    along the estimate's long axis (its yaw, modulo pi: the nearer of the two). Round objects: keep the yaw."""
    if size is None or abs(size.x - size.y) < ROUND_TOLERANCE_M:
        return current_yaw
    a = wrap(est_yaw)
    b = wrap(est_yaw + math.pi)
    return a if abs(wrap(a - current_yaw)) <= abs(wrap(b - current_yaw)) else b



# --------------------------------------------------------------------------- manipulation routines


class _Manipulation(Skill):
    category: ClassVar[Category] = "manipulation"

    def view_height(self, target_z: float) -> float:
        """Body altitude at the standoff that puts a target at `target_z` near the image centre."""
        s = self.settings
        cam_dist = max(s.standoff_distance - 0.12, 0.2)
        z = target_z + cam_dist * math.tan(math.radians(s.camera_pitch_deg)) + 0.05
        return min(max(z, s.min_altitude, target_z + 0.35), s.max_altitude)

    def standoff(self, ctx: SkillContext, target: Vec3, st: VehicleState) -> tuple[Vec3, float]:
        """A point `standoff_distance` from the target on the vehicle's side, facing it, inside the geofence."""
        s = self.settings
        dx, dy = st.position.x - target.x, st.position.y - target.y
        base = math.atan2(dy, dx) if math.hypot(dx, dy) > 0.05 else wrap(st.yaw + math.pi)
        z = self.view_height(target.z)
        for k in (0, 1, -1, 2, -2, 3, -3, 4, -4, 5, -5, 6):
            ang = base + k * math.radians(30.0)
            p = Vec3(x=target.x + s.standoff_distance * math.cos(ang), y=target.y + s.standoff_distance * math.sin(ang),
                     z=z)
            if geofence_problem(p, s) is None:
                return p, wrap(ang + math.pi)
        raise SkillFailed(f"no standoff point inside the geofence around {fmt(target)}")

    async def travel(self, ctx: SkillContext, target: Vec3, yaw: float, what: str) -> VehicleState:
        """Climb first when below the target height, cross at constant height, then settle vertically: the
        horizontal leg never runs lower than either end."""
        s = self.settings
        st = ctx.current()
        cross_z = max(st.position.z, target.z)
        if st.position.z < cross_z - s.position_tolerance:
            st = await ctx.goto(Vec3(x=st.position.x, y=st.position.y, z=cross_z), st.yaw, s.descent_speed,
                                what=f"{what} (climb)")
        problem = self.leg_problem(ctx, st, target, cross_z)
        if problem:
            raise SkillFailed(f"{what}: {problem}")
        st = await ctx.goto(Vec3(x=target.x, y=target.y, z=cross_z), yaw, s.approach_speed, what=what)
        if abs(st.position.z - target.z) > s.position_tolerance:
            st = await ctx.goto(target, yaw, s.descent_speed, what=f"{what} (height)")
        return st

    def leg_problem(self, ctx: SkillContext, st: VehicleState, target: Vec3, cross_z: float) -> str | None:
        """Clearance of a horizontal transit leg, with a held object's extent below the gripper: checked on the
        latest depth image when the leg runs within the camera's view (the camera looks forward only); the
        last `clearance_margin` + 0.3 m, where the routine descends onto its target, is not part of the leg."""
        s = self.settings
        dx, dy = target.x - st.position.x, target.y - st.position.y
        length = math.hypot(dx, dy) - s.clearance_margin - 0.3
        if length <= 0.1 or abs(wrap(math.atan2(dy, dx) - st.yaw)) > math.radians(30):
            return None
        clearance = ctx.clearance
        if clearance.depth is None or clearance.age_s > s.depth_max_age_s:
            return None  # nothing seen to check against (the geofence and altitude band still apply)
        held = ctx.memory.held_size if ctx.memory.held else None
        below = s.clearance_below if held is None else max(s.clearance_below, -s.gripper_offset_z + held.z + 0.05)
        dist, _n = clearance.nearest_ahead(cross_z, s, length, below)
        if dist is None:
            return None
        return (f"obstacle {dist:.2f} m ahead on a {length:.2f} m transit leg at {cross_z:.2f} m"
                + (" (with the held object below the gripper)" if held is not None else "")
                + "; nothing was moved past it: climb or go around first")

    def timeout_s(self, ctx: SkillContext, argument: str | None) -> float:
        return self.settings.grasp_timeout_s


def _top(o: MemoryObject | ObjectEstimate) -> float:
    if o.top_z is not None:
        return o.top_z
    pos = o.position if isinstance(o, MemoryObject) else o.pose.position  # type: ignore[union-attr]
    return pos.z + (o.size.z / 2 if o.size is not None else 0.05)


@register
class Grasp(_Manipulation):
    """Skill grasp: approach, re-localize, descend on the localized object, close the gripper and verify the hold."""

    name = names.GRASP
    description = ("Pick up the localized object: approach a standoff {s.standoff_distance:g} m from it facing it, "
                   "re-localize with yaw alignment, move above it, descend, close the gripper, verify it is held, "
                   "and retreat to {s.flight_altitude:g} m. Needs a recent obj_localization of the object.")
    argument = "object label (optional; defaults to the last localized object)"

    def parameters(self) -> tuple[SkillParameter, ...]:
        s = self.settings
        return (SkillParameter(name="standoff", value=s.standoff_distance, unit="m"),
                SkillParameter(name="reach", value=s.reach, unit="m"),
                SkillParameter(name="max_localization_age", value=s.localization_max_age_s, unit="s"),
                SkillParameter(name="descent_speed", value=s.descent_speed, unit="m/s"))

    def check(self, ctx: SkillContext, argument: str | None) -> str | None:
        s, mem = self.settings, ctx.memory
        if mem.held:
            return f"already holding the {mem.held}: place it before grasping something else"
        st = ctx.state.value
        if st is not None and st.gripper == GripperState.CLOSED and st.gripper_holding:
            # The autopilot's word over memory (which a restart empties): opening now would drop it.
            return ("the gripper reports an object between its fingers: place it on a localized surface before "
                    "grasping something else (the gripper never opens in the air except to place)")
        obj = mem.find_object(argument)
        if obj is None:
            what = f"the {argument}" if argument else "any object"
            return f"no localization of {what} in working memory: run obj_localization first"
        a = age_s(obj)
        if a > s.localization_max_age_s:
            return (f"the {obj.label} was last localized {a:.0f} s ago (limit {s.localization_max_age_s:.0f} s): "
                    "run obj_localization again")
        far = beyond_reach(ctx, obj.position, s.reach, f"the {obj.label}",
                           ", where localization is accurate enough for the gripper")
        if far:
            return far
        if obj.size is not None and min(obj.size.x, obj.size.y) > s.gripper_max_opening - 0.01:
            return (f"the {obj.label} measures {100 * min(obj.size.x, obj.size.y):.0f} cm across its narrow side: "
                    f"wider than the gripper opens ({100 * s.gripper_max_opening:.0f} cm)")
        return None

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        s, mem = self.settings, ctx.memory
        obj = mem.find_object(argument)
        if obj is None:
            raise SkillFailed("the object disappeared from working memory")
        label, query = obj.label, obj.query or obj.label
        st = ctx.current()
        if st.gripper != GripperState.OPEN:
            await ctx.gripper("open")

        # Iterative re-localization from a standoff, facing the object (it is invisible from right above).
        remembered = obj.position
        est_pos, est_top, size, yaw = obj.position, _top(obj), obj.size, 0.0
        for _ in range(max(1, s.relocalize_iterations)):
            sp, yaw = self.standoff(ctx, est_pos, ctx.current())
            await self.travel(ctx, sp, yaw, f"standoff facing the {label}")
            est = await ctx.localize_object(query)
            if not est.found or est.pose is None:
                mem.forget_object(label)
                raise SkillFailed(f"grasp aborted before contact: {not_found(label, est)} from the standoff at its "
                                  f"remembered position {fmt(remembered)}; it may have moved: localize it again")
            shift = horizontal_distance(est.pose.position, remembered)
            if shift > s.max_object_shift:
                mo = mem.store_object(est, query)
                raise SkillFailed(f"grasp aborted before contact: the {label} moved since it was localized "
                                  f"(remembered {fmt(remembered)}, now {fmt(mo.position)}, {shift:.2f} m); memory "
                                  "updated, grasp again or re-localize")
            step = horizontal_distance(est.pose.position, est_pos)
            mo = mem.store_object(est, query)
            est_pos, est_top, size = mo.position, _top(mo), mo.size or size
            if step < s.relocalize_converged:
                break
        ctx.note(f"{label} re-localized at {fmt(est_pos)}")

        # Align the fingers with the object's estimated yaw (they close across its short side), above it, then
        # a controlled descent, slower for the last part, that puts the pads around the object's top part.
        height = size.z if size is not None else 0.1
        est_yaw = mo.yaw if isinstance(mo, MemoryObject) else 0.0
        yaw = grasp_yaw(size, est_yaw, yaw)
        grip_z = est_top - grip_depth(height, s.grasp_depth_fraction)
        body_z = grip_z - s.gripper_offset_z
        hover = Vec3(x=est_pos.x, y=est_pos.y, z=max(ctx.current().position.z, body_z + FINAL_DESCENT_M))
        await ctx.goto(hover, yaw, s.approach_speed, what=f"above the {label}")
        near = Vec3(x=est_pos.x, y=est_pos.y, z=body_z + FINAL_DESCENT_M)
        if hover.z > near.z + s.position_tolerance:
            await ctx.goto(near, yaw, s.descent_speed, low=s.manipulation_min_altitude,
                           what=f"above the {label} (descent)")
        grip = Vec3(x=est_pos.x, y=est_pos.y, z=body_z)
        await ctx.goto(grip, yaw, s.final_descent_speed, low=s.manipulation_min_altitude,
                       what=f"grasp height over the {label}")
        with contextlib.suppress(TimeoutError):
            await ctx.wait_for(lambda st: math.dist(st.position.as_tuple(), grip.as_tuple()) <= GRASP_SETTLE_M,
                               GRASP_SETTLE_TIMEOUT_S, "grasp point")
        await ctx.gripper("close")
        sensed = ctx.current().gripper_width is not None
        if sensed:
            # The gripper's own sensing: both pads in contact at an opening that fits the object.
            try:
                st = await ctx.wait_for(lambda st: bool(st.gripper_holding), s.gripper_timeout_s, "fingers closing")
            except TimeoutError:
                st = ctx.current()
            if not st.gripper_holding:
                await ctx.gripper("open")
                raise SkillFailed(f"grasp missed: the fingers closed to {100 * (st.gripper_width or 0):.1f} cm "
                                  f"without holding the {label}; gripper reopened, localize it again and retry")
            ctx.note(f"fingers hold the {label} at {100 * (st.gripper_width or 0):.1f} cm")
        up = max(s.flight_altitude, hover.z)
        await ctx.goto(Vec3(x=est_pos.x, y=est_pos.y, z=up), yaw, s.descent_speed, what="retreat height")
        if sensed:
            st = ctx.current()
            if not st.gripper_holding:
                await ctx.gripper("open")
                mem.forget_object(label)
                raise SkillFailed(f"grasp failed: the {label} slipped out of the fingers while lifting (opening "
                                  f"{100 * (st.gripper_width or 0):.1f} cm); gripper reopened, localize it again")
            mem.forget_object(label)
            mem.set_held(label, size)
            end = ctx.current()
            return SkillResult(f"grasped the {label} (fingers at {100 * (end.gripper_width or 0):.1f} cm, in "
                               f"contact); holding it at {fmt(end.position)}")

        # No gripper sensing (an autopilot that does not report it): from the standoff, the old spot must now
        # be empty.
        sp, yaw = self.standoff(ctx, est_pos, ctx.current())
        await self.travel(ctx, Vec3(x=sp.x, y=sp.y, z=max(sp.z, ctx.current().position.z)), yaw, "verification view")
        check = await ctx.localize_object(query)
        if check.found and check.pose is not None and horizontal_distance(check.pose.position, est_pos) <= \
                s.verify_tolerance:
            mem.store_object(check, query)
            await ctx.gripper("open")
            raise SkillFailed(f"grasp missed: the {label} is still at {fmt(check.pose.position)} after closing the "
                              "gripper; gripper reopened, try grasp again")
        mem.forget_object(label)
        mem.set_held(label, size)
        ctx.note(f"{label} no longer at {fmt(est_pos)}: held")
        end = ctx.current()
        return SkillResult(f"grasped the {label}; holding it at {fmt(end.position)}")


@register
class Place(_Manipulation):
    """Skill place: descend to the localized placement spot, release the held object and verify it rests there."""

    name = names.PLACE
    description = ("Place the held object at the localized placement spot: approach above it, controlled descent "
                   "until the object's bottom is {s.place_vertical_offset:g} m above the surface, open the gripper, "
                   "retreat to {s.flight_altitude:g} m and verify the object rests there. Needs a held object and "
                   "a placement_localization.")
    argument = "surface label (optional; defaults to the last placement spot)"

    def timeout_s(self, ctx: SkillContext, argument: str | None) -> float:
        return self.settings.place_timeout_s

    def check(self, ctx: SkillContext, argument: str | None) -> str | None:
        s, mem = self.settings, ctx.memory
        if not mem.held:
            return "not holding any object: grasp one first"
        pl = mem.find_placement(argument)
        if pl is None:
            what = f"on the {argument}" if argument else ""
            return f"no placement spot {what} in working memory: run placement_localization first".replace("  ", " ")
        return beyond_reach(ctx, pl.position, s.place_reach, f"the placement spot on the {pl.label}")

    async def run(self, ctx: SkillContext, argument: str | None) -> SkillResult:
        s, mem = self.settings, ctx.memory
        pl = mem.find_placement(argument)
        held = mem.held
        if pl is None or held is None:
            raise SkillFailed("placement spot or held object vanished from working memory")
        height = mem.held_size.z if mem.held_size is not None else 0.1
        surface_z = pl.top_z if pl.top_z is not None else pl.position.z
        bottom = max(pl.position.z, surface_z + s.place_vertical_offset)
        # The object hangs with the gripper point grip_depth below its top (as grasp took it).
        body_z = bottom + height - grip_depth(height, s.grasp_depth_fraction) - s.gripper_offset_z
        st = ctx.current()
        transit = max(st.position.z, s.flight_altitude, body_z)
        yaw = st.yaw
        spot = Vec3(x=pl.position.x, y=pl.position.y, z=transit)
        await self.travel(ctx, spot, yaw, f"above the {pl.label} spot")
        await ctx.goto(Vec3(x=spot.x, y=spot.y, z=body_z), yaw, s.descent_speed, low=s.manipulation_min_altitude,
                       what=f"release height over the {pl.label}")
        await ctx.gripper("open")
        if ctx.current().gripper_width is not None:
            # Verify the release with the gripper's sensing: no pad in contact any more.
            try:
                await ctx.wait_for(lambda st: st.gripper_holding is False, s.gripper_timeout_s, "release")
            except TimeoutError as exc:
                raise SkillFailed(f"the {held} did not come free of the opened fingers") from exc
        mem.set_held(None)
        await ctx.goto(Vec3(x=spot.x, y=spot.y, z=max(s.flight_altitude, body_z)), yaw, s.descent_speed,
                       what="retreat height")

        # Verify: back off, look at the spot, the object must rest there.
        target = Vec3(x=pl.position.x, y=pl.position.y, z=bottom + height / 2)
        sp, vyaw = self.standoff(ctx, target, ctx.current())
        await self.travel(ctx, Vec3(x=sp.x, y=sp.y, z=max(sp.z, s.min_altitude)), vyaw, "verification view")
        est = await ctx.localize_object(held)
        if not est.found or est.pose is None:
            raise SkillFailed(f"released the {held} over the {pl.label} but could not see it there afterwards: "
                              f"{not_found(held, est)}")
        off = horizontal_distance(est.pose.position, pl.position)
        bottom_seen = est.pose.position.z - (est.size.z / 2 if est.size is not None else height / 2)
        mo = mem.store_object(est, held)
        if off > s.place_tolerance or abs(bottom_seen - surface_z) > 0.1:
            raise SkillFailed(f"released the {held} but it lies at {fmt(mo.position)}, {off:.2f} m from the "
                              f"placement spot on the {pl.label}")
        ctx.note(f"{held} rests on the {pl.label} at {fmt(mo.position)}")
        return SkillResult(f"placed the {held} on the {pl.label} at {fmt(mo.position)}")
