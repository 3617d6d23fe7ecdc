"""When to close the gripper on a wandering hover: where the object sits on the pads when they reach it.

Usage: .venv/bin/python benchmarks/close_timing.py [--seeds 0-19] [--trials 15] [--leads 0,0.4] [--width 0.08]

The executor closes once the gripper point has stayed inside its window for `align_samples` state samples
(`services/executor/skills/manipulation.py`, `in_window`). The pads then take (18 cm - width) / 0.15 m/s to reach
the object (0.67 s for an 8 cm fruit: the simulator's gripper), and the hover keeps wandering. An object more than
the pad's half-width (2.5 cm) off the pads' centre along their width is held on the pad's edge, and a fruit held
there falls out in transit. This measures that offset for each `lead` (the executor's `close_lead_s`: the gripper
point carried that long at its present velocity must be inside the window too).

In-process, no rendering: the MuJoCo multirotor of the `realistic` level (a fresh noise seed per layout seed:
estimate bias and noise, air, thrust noise), holding a position setpoint in its own estimate frame as the
autopilot does; the object is taken to be exactly where the estimate frame put it `--blind` seconds before the
wait for the window begins (a perfect last detection, then the blind leg to it), so the figure is the share of the
error that the close's timing governs: the estimate's drift since the detection (a longer wait drifts further),
the offset the trigger accepted and the vehicle's motion during the close. The hover stands in for the blind leg
(the leg itself flies at 0.25 m/s and is not modelled). Offsets of the body origin (the gripper hangs rigidly
under it; its tilt adds ~0.4 cm, not modelled here). The same seeds and trials for every lead (paired). The
vehicle's state is sampled at the bridge's default state rate.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._figures import add_json_option, write_json  # noqa: E402
from services.autopilot_bridge.settings import BridgeSettings  # noqa: E402
from services.executor.settings import ExecutorSettings  # noqa: E402
from services.executor.skills.manipulation import in_window  # noqa: E402
from services.sim.core import SimCore  # noqa: E402
from services.sim.physics import CLOSING_SPEED, FINGER_MAX_OPENING, FINGER_PAD  # noqa: E402
from services.sim.vehicle import realism_params  # noqa: E402
from shared.messages import Scenario  # noqa: E402
from tests.sim.flight import Clock, to_offboard  # noqa: E402


def seeds_arg(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def trials_for(seed: int, lead: float, trials: int, width: float, blind: float) -> list[tuple[float, float, bool]]:
    """(offset along the pad width when the pads reach the object, wait before the close, aligned) per trial."""
    ex_s, rate = ExecutorSettings(), BridgeSettings().state_rate_hz
    window = (ex_s.grasp_window_x, ex_s.grasp_window_y)
    core = SimCore(Scenario(seed=seed), realism_params("realistic", seed=seed), realism="realistic",
                   dynamics="multirotor")
    clock = Clock(core)
    to_offboard(core, clock, 1.0, tolerance=0.15)
    v = core.vehicle
    yaw = 0.0  # ENU: body x (the pad width) along world x
    sp = v.position_enu().copy()
    clock.fly(sp, yaw, 3.0)
    contact_s = (FINGER_MAX_OPENING - width) / CLOSING_SPEED
    out = []
    for _ in range(trials):
        bias0 = v.position_enu() - v.true_position_enu()  # the last detection: the object at sp in this frame
        clock.fly(sp, yaw, blind)
        run = waited = 0
        limit = int(ex_s.align_timeout_s * rate)
        while run < ex_s.align_samples and waited < limit:
            clock.fly(sp, yaw, 1.0 / rate)
            waited += 1
            e = sp - v.position_enu()
            vel = np.array([v.v[1], v.v[0]])  # NED -> ENU, horizontal
            slow = math.hypot(*vel) <= ex_s.settle_speed
            run = run + 1 if slow and in_window(e[0], e[1], vel[0], vel[1], yaw, window, lead) else 0
        clock.fly(sp, yaw, contact_s)
        off = v.true_position_enu() - (sp - bias0)  # the object's true position: sp in the detection's frame
        out.append((float(off[0]), waited / rate, run >= ex_s.align_samples))
        clock.fly(sp, yaw, 1.0)  # the next trial from an unrelated moment of the hover
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=seeds_arg, default=seeds_arg("0-19"), help="noise seeds, e.g. 0-19")
    ap.add_argument("--trials", type=int, default=15, help="closes per seed")
    ap.add_argument("--leads", default="0,0.4", help="comma-separated leads (s); the first is the baseline")
    ap.add_argument("--width", type=float, default=0.08, help="object width across the pads (m)")
    ap.add_argument("--blind", type=float, default=1.6,
                    help="seconds from the last detection to the start of the wait (dev grasp runs: 1.4-3.7 s)")
    add_json_option(ap)
    a = ap.parse_args()
    leads = [float(t) for t in a.leads.split(",")]
    edge = FINGER_PAD[0]
    figures: dict[str, dict[str, float]] = {}
    print(f"pads reach a {100 * a.width:.0f} cm object {(FINGER_MAX_OPENING - a.width) / CLOSING_SPEED:.2f} s after "
          f"the close; pad half-width {100 * edge:.1f} cm; last detection {a.blind:.1f} s before the wait; "
          f"{len(a.seeds)} seeds x {a.trials} closes per lead")
    for lead in leads:
        rows: list[tuple[float, float, bool]] = []
        for i, seed in enumerate(a.seeds):
            rows += trials_for(seed, lead, a.trials, a.width, a.blind)
            print(f"  lead {lead:.2f} s: seed {seed} ({i + 1}/{len(a.seeds)})", file=sys.stderr, flush=True)
        off = np.abs([r[0] for r in rows])
        figures[f"{lead:g}"] = {
            "closes": len(rows),
            "offset_median_cm": float(100 * np.median(off)),
            "offset_p90_cm": float(100 * np.percentile(off, 90)),
            "beyond_pad_edge_share": float(np.mean(off > edge)),
            "wait_median_s": float(np.median([r[1] for r in rows])),
            "aligned_within_timeout_share": float(np.mean([r[2] for r in rows])),
        }
    base = figures[f"{leads[0]:g}"]
    print(f"{'lead s':>7} {'closes':>6} {'|x| median':>10} {'p90':>7} {'beyond edge':>11} {'ratio':>6} "
          f"{'wait':>6} {'aligned':>7}")
    for lead in leads:
        f = figures[f"{lead:g}"]
        share, base_share = f["beyond_pad_edge_share"], base["beyond_pad_edge_share"]
        ratio = share / base_share if base_share else math.nan
        print(f"{lead:7.2f} {f['closes']:6.0f} {f['offset_median_cm']:8.2f}cm {f['offset_p90_cm']:5.2f}cm "
              f"{100 * f['beyond_pad_edge_share']:10.1f}% {ratio:5.2f}x {f['wait_median_s']:5.2f}s "
              f"{100 * f['aligned_within_timeout_share']:6.1f}%")
    write_json(a.json, "close_timing", figures, a)


if __name__ == "__main__":
    main()
