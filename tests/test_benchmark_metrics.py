"""The benchmark's per-trial measures (evaluation/metrics.trial_measures) on hand-made trials:
frozen, the path-free look-ahead, impact speed relative to what was hit and its Euro NCAP band,
the CARLA driving score, drive-off from rest; and their summary over trials."""

import numpy as np
import pytest

from racecav.evaluation import metrics as M
from racecav.evaluation.results import Measures, Stats, Trial, measure_summary, summarize

CAR = (0.55, 0.3)
DT = 0.1


def _ego(speeds, x0=0.0, y=0.0, yaw=0.0):
    """(t, poses, world velocities) of an ego driving along yaw at the given speed per step."""
    v = np.asarray(speeds, float)
    t = np.arange(len(v)) * DT
    s = x0 + np.concatenate([[0.0], np.cumsum(v[:-1] * DT)])
    ego = np.stack([s * np.cos(yaw), y + s * np.sin(yaw), np.full(len(v), yaw)], -1)
    vel = np.stack([v * np.cos(yaw), v * np.sin(yaw)], -1)
    return t, ego, vel


def _measure(t, ego, vel, obstacles=(), collided=False, contact_with="", progress=5.0, route=4.0, success=None):
    if success is None:
        success = not collided and progress >= route
    return M.trial_measures(t, ego, vel, [np.asarray(o, float) for o in obstacles], [CAR] * len(obstacles), CAR,
                            collided, contact_with, progress, route, success)


def _parked(x, y, n, yaw=0.0):
    return np.tile([x, y, yaw, 0.0], (n, 1))


def test_standing_with_a_free_path_is_frozen_and_a_blocked_path_is_not():
    speeds = [0.0] * 30 + [1.5] * 40  # stands 3 s, then drives on and gets through
    t, ego, vel = _ego(speeds)
    m = _measure(t, ego, vel)
    assert m.frozen and m.frozen_reason == "standing" and m.longest_free_standing_s == pytest.approx(2.9)
    # a car parked 1 m ahead in its lane: waiting behind it is not frozen
    m = _measure(t, ego, vel, [_parked(1.0, 0.0, len(t))])
    assert not m.frozen and m.longest_free_standing_s < 0.1
    # the same car beside the road (1 m to the left, out of the corridor): frozen again
    m = _measure(t, ego, vel, [_parked(1.0, 1.0, len(t))])
    assert m.frozen and m.frozen_reason == "standing"
    # standing 1.5 s with nothing about: not yet frozen
    t, ego, vel = _ego([0.0] * 15 + [1.5] * 40)
    assert not _measure(t, ego, vel).frozen


def test_path_free_looks_ahead_in_time():
    """A crossing car that will be in the corridor within 1 s makes the path not free now: yielding to
    a car about to pass is not frozen, standing on once it has gone is."""
    n = 60
    t, ego, vel = _ego([0.0] * n)  # stands at x = 0 facing +x the whole 6 s
    cross = np.zeros((n, 4))
    cross[:, 0] = 0.275 + 0.6            # its centre line 0.6 m ahead of the ego's bumper
    cross[:, 1] = -3.0 + 1.0 * t           # northbound at 1 m/s: in the corridor at about t 2.6-3.4 s
    cross[:, 2], cross[:, 3] = np.pi / 2, 1.0
    free = M.path_free(t, ego, CAR, [cross], [CAR])
    occupied = np.abs(cross[:, 1]) < (CAR[1] / 2 + M.PATH_MARGIN_M + CAR[0] / 2)
    first = int(np.flatnonzero(occupied)[0])
    assert not free[first - 9] and free[first - 11]  # 1 s of look-ahead (10 steps)
    assert not free[occupied].any() and free[-1]
    m = _measure(t, ego, vel, [cross], progress=0.0, success=False)
    # standing 0-1.5 s (free) and from about 3.5 s (free, 2.4 s): frozen by standing, and short of its route
    assert m.frozen and m.frozen_reason == "standing" and 2.0 < m.longest_free_standing_s < 2.6
    m = _measure(t[:45], ego[:45], vel[:45], [cross[:45]], progress=0.0, success=False)
    assert m.frozen and m.frozen_reason == "short" and m.longest_free_standing_s < 2.0  # time up: frozen anyway


def test_impact_speed_is_relative_to_what_was_hit():
    t, ego, vel = _ego([2.0] * 20)
    ahead = np.stack([ego[:, 0] + 0.6, ego[:, 1], np.zeros(20), np.full(20, 1.5)], -1)  # a slower lead
    m = _measure(t, ego, vel, [ahead], collided=True, contact_with="car1", progress=3.8)
    assert m.impact_speed_mps == pytest.approx(0.5) and m.impact_band == 1 and m.infraction == "vehicle"
    oncoming = np.stack([ego[:, 0] + 0.6, ego[:, 1], np.full(20, np.pi), np.full(20, 1.0)], -1)
    m = _measure(t, ego, vel, [ahead, oncoming], collided=True, contact_with="car2", progress=3.8)
    assert m.impact_speed_mps == pytest.approx(3.0) and m.impact_band == 3
    m = _measure(t, ego, vel, collided=True, contact_with="wall", progress=3.8)
    assert m.impact_speed_mps == pytest.approx(2.0) and m.impact_band == 2 and m.infraction == "static"
    # the bands: Euro NCAP's 5 / 15 / 30 / 40 km/h at 1/10 Froude scale
    assert M.IMPACT_BANDS_MPS == (0.44, 1.32, 2.64, 3.51)
    assert [M.impact_band(v) for v in (0.0, 0.43, 0.44, 1.4, 2.7, 3.6)] == [0, 0, 1, 2, 3, 4]
    assert _measure(t, ego, vel).impact_speed_mps is None


def test_carla_driving_score():
    t, ego, vel = _ego([1.0] * 20)
    assert _measure(t, ego, vel, progress=4.5).driving_score == 1.0  # success: route complete, no infraction
    car = _measure(t, ego, vel, [_parked(9, 9, 20)], collided=True, contact_with="car1", progress=2.0)
    assert car.route_completion == 0.5 and car.driving_score == pytest.approx(0.5 * 0.6)
    wall = _measure(t, ego, vel, collided=True, contact_with="wall", progress=2.0)
    assert wall.driving_score == pytest.approx(0.5 * 0.65)
    late = _measure(t, ego, vel, progress=1.0)
    assert late.infraction == "timeout" and late.frozen and late.frozen_reason == "short"
    assert late.driving_score == pytest.approx(0.25 * 0.7)
    assert _measure(t, ego, vel, collided=True, contact_with="wall", progress=-0.3).driving_score == 0.0


def test_drive_off_from_rest():
    t, ego, vel = _ego([0.0] * 8 + [0.1, 0.15, 0.25, 0.5] + [1.0] * 30)
    m = _measure(t, ego, vel)
    assert m.from_rest and m.drive_off_s == pytest.approx(1.0)
    t, ego, vel = _ego([0.0] * 40)
    m = _measure(t, ego, vel, progress=0.0)
    assert m.from_rest and m.drive_off_s is None and m.frozen
    t, ego, vel = _ego([1.0] * 40)
    m = _measure(t, ego, vel)
    assert not m.from_rest and m.drive_off_s is None


def test_summary_of_measures_and_old_trials_without_them():
    ms = [Measures(frozen=True, frozen_reason="short", infraction="timeout", route_completion=0.5,
                   driving_score=0.35, from_rest=True),
          Measures(impact_speed_mps=1.0, impact_band=1, infraction="vehicle", route_completion=0.5,
                   driving_score=0.3, from_rest=True, drive_off_s=0.4),
          Measures(route_completion=1.0, driving_score=1.0)]
    s = measure_summary(ms)
    assert s["measured"] == 3 and s["frozen"] == 1 and s["timeouts"] == 1
    assert s["impact_bands"] == [0, 1, 0, 0, 0] and s["median_impact_speed_mps"] == 1.0
    assert s["from_rest"] == 2 and s["never_drove_off"] == 1 and s["median_drive_off_s"] == 0.4
    assert s["mean_driving_score"] == pytest.approx(1.65 / 3)
    old = Trial(index=0, seed=0, success=True, collided=False, contact_with="", contact_time_s=None, end_time_s=4.0,
                progress_m=5.0, min_gap_m=None, min_center_distance_m=None, steps=40, commands=40,
                latency_ms=Stats(n=0), compute_ms=Stats(n=0), wall_s=1.0)
    assert old.measures is None and summarize([old]).measured == 0 and summarize([old]).frozen is None
    new = old.model_copy(update={"measures": ms[2]})
    assert summarize([old, new]).measured == 1 and summarize([old, new]).mean_driving_score == 1.0
