"""Pure protocol pieces of the bridge: frames, PX4 modes, setpoint fields, ramps, statistics."""

from __future__ import annotations

import math

import pytest

from services.autopilot_bridge import px4
from services.autopilot_bridge.stream import SetpointStream, Target, percentile


def test_ned_enu_round_trip_and_axes() -> None:
    # 1 m north, 2 m east, 3 m down = 2 m east (x), 1 m north (y), 3 m below (z).
    assert px4.ned_to_enu(1.0, 2.0, 3.0) == (2.0, 1.0, -3.0)
    assert px4.enu_to_ned(*px4.ned_to_enu(0.3, -4.0, -1.5)) == (0.3, -4.0, -1.5)


@pytest.mark.parametrize(("ned", "enu"), [(0.0, math.pi / 2), (math.pi / 2, 0.0), (math.pi, -math.pi / 2),
                                          (-math.pi / 2, math.pi)])
def test_yaw_conversion(ned: float, enu: float) -> None:
    assert math.isclose(px4.wrap_pi(px4.yaw_ned_to_enu(ned) - enu), 0.0, abs_tol=1e-12)
    assert math.isclose(px4.wrap_pi(px4.yaw_enu_to_ned(enu) - ned), 0.0, abs_tol=1e-12)


def test_wrap_pi_range() -> None:
    for a in (-10.0, -math.pi, 0.0, math.pi, 3 * math.pi, 7.5):
        w = px4.wrap_pi(a)
        assert -math.pi < w <= math.pi
        assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9)
        assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-9)


def test_custom_mode_codec() -> None:
    assert px4.decode_custom_mode(6 << 16) == "OFFBOARD"
    assert px4.decode_custom_mode((4 << 16) | (2 << 24)) == "AUTO.TAKEOFF"
    assert px4.decode_custom_mode((4 << 16) | (6 << 24)) == "AUTO.LAND"
    assert px4.decode_custom_mode(3 << 16) == "POSCTL"
    assert px4.decode_custom_mode(99 << 16).startswith("UNKNOWN")
    for name in ("OFFBOARD", "AUTO.LOITER", "AUTO.LAND", "POSCTL", "AUTO.TAKEOFF"):
        assert px4.decode_custom_mode(px4.encode_custom_mode(name)) == name
    assert px4.set_mode_params("AUTO.LOITER") == (1.0, 4.0, 3.0)
    with pytest.raises(ValueError, match="unknown PX4 mode"):
        px4.set_mode_params("WARP")


def test_result_names() -> None:
    assert px4.result_name(0) == "MAV_RESULT_ACCEPTED"
    assert px4.result_name(2) == "MAV_RESULT_DENIED"
    assert px4.result_name(None) == ""
    assert px4.result_name(42) == "MAV_RESULT_42"


def test_setpoint_fields_are_ned_with_position_yaw_mask() -> None:
    sp = px4.SetpointNED.from_enu(1.0, 2.0, 1.5, 0.0)  # east 1, north 2, up 1.5, facing east
    f = sp.fields(123, 1, 1)
    assert f[3] == px4.MAV_FRAME_LOCAL_NED and f[4] == 2552
    assert f[5:8] == (2.0, 1.0, -1.5)
    assert math.isclose(f[14], math.pi / 2)  # facing east is yaw 90 deg in NED


def test_target_ramp_moves_at_speed_and_ends_on_goal() -> None:
    t = Target(4.0, 0.0, 1.0, 0.5, start=(0.0, 0.0, 1.0), speed=2.0, t0=10.0)
    assert t.at(10.0)[:3] == (0.0, 0.0, 1.0)
    assert t.at(11.0)[:3] == pytest.approx((2.0, 0.0, 1.0))
    assert t.at(13.0) == (4.0, 0.0, 1.0, 0.5)
    assert not t.ramp_done(11.0) and t.ramp_done(12.0)
    assert Target(1.0, 2.0, 3.0, 0.0).at(0.0) == (1.0, 2.0, 3.0, 0.0)


def test_percentile_nearest_rank() -> None:
    vals = [float(i) for i in range(1, 101)]
    assert percentile(vals, 50) == 50.0
    assert percentile(vals, 99) == 99.0
    assert percentile([3.0], 99) == 3.0


def test_stream_stats_report_jitter_from_intervals() -> None:
    s = SetpointStream(lambda sp: True, 20.0)
    s._intervals.extend([0.050] * 98 + [0.053, 0.060])
    st = s.stats()
    assert st["interval_p50_ms"] == pytest.approx(50.0)
    assert st["jitter_p99_ms"] == pytest.approx(3.0)
    assert st["jitter_max_ms"] == pytest.approx(10.0)


def test_stream_sends_current_target_until_stopped() -> None:
    got: list[px4.SetpointNED] = []
    s = SetpointStream(lambda sp: got.append(sp) is None, 50.0)
    s.start(Target(1.0, 2.0, 3.0, 0.0))
    import time

    deadline = time.monotonic() + 10
    while len(got) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    s.set_target(Target(5.0, 6.0, 7.0, 0.0))
    n = len(got)
    while len(got) < n + 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    s.stop()
    assert got[0] == px4.SetpointNED(2.0, 1.0, -3.0, math.pi / 2)
    assert got[-1].x == 6.0 and got[-1].z == -7.0
    stopped = len(got)
    time.sleep(0.1)
    assert len(got) == stopped and not s.running
