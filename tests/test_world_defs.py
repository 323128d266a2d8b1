"""The shared world definition: car, lidar, worlds and scenarios load, validate and agree."""

import math

import numpy as np
import pytest

from racecav.common.lidar import LidarSpec, make_scan, ray_angles, sanitize, scan_ranges
from racecav.common.scenario import load_scenario, scenario_names
from racecav.common.vehicle import (load_car, steer_from_action, throttle_from_action,
                                    wheel_speed_step)
from racecav.common.world import load_world, segment_distance


def test_car_loads_and_friction_model_settles_at_autovrl_speed():
    car = load_car("slash")
    assert car.wheelbase == 0.325 and car.delta_min < 0 < car.delta_max
    w = np.zeros(3)
    for _ in range(2000):  # 50 s at the physics step
        w = wheel_speed_step(w, np.array([1.0, 0.5, 0.0]), car.physics_dt, car)
    assert w[0] == pytest.approx(car.w_max, rel=1e-3)
    assert 35.0 < car.w_max < 36.5  # AutoVRL: ~35.8 rad/s at full throttle
    assert 0 < w[1] < w[0] and w[2] == 0.0
    assert steer_from_action(5.0, car) == car.delta_max and steer_from_action(-5.0, car) == car.delta_min
    assert throttle_from_action(-0.3) == 0.0 and throttle_from_action(0.4) == pytest.approx(0.4)
    from racecav.common.vehicle import steady_speed, throttle_for_speed
    assert steady_speed(1.0, car) == pytest.approx(car.v_max)
    t = throttle_for_speed(1.0, car, car.agent_speed_scale)
    assert steady_speed(t, car, car.agent_speed_scale) == pytest.approx(1.0)
    w = 0.0
    for _ in range(4000):  # the friction model does settle there
        w = wheel_speed_step(w, t, car.physics_dt, car)
    assert w * car.wheel_radius * car.agent_speed_scale == pytest.approx(1.0, rel=1e-3)


def test_car_file_errors_name_the_field(tmp_path):
    from racecav.common.vehicle import CARS_DIR
    text = (CARS_DIR / "slash.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("wheelbase = 0.325", "wheelbase = -1"))
    with pytest.raises(ValueError, match="wheelbase"):
        load_car(bad)


def test_lidar_order_and_preprocessing():
    spec = LidarSpec()
    a = ray_angles(spec)
    assert a.shape == (170,) and a[0] == pytest.approx(-math.pi / 4) and a[-1] == pytest.approx(math.pi / 4)
    assert np.all(np.diff(a) > 0)  # counter-clockwise: index 0 is the rightmost ray
    r = scan_ranges(np.array([1.0, 20.0, 0.01]), np.array([True, True, False]), spec)
    assert r[0] == 1.0 and np.isinf(r[1]) and np.isinf(r[2])
    obs = sanitize(np.array([np.inf, np.nan, 0.01, 3.0, 50.0], np.float32), spec)
    assert obs.tolist() == pytest.approx([12.0, 12.0, 0.05, 3.0, 12.0])
    scan = make_scan(np.full(170, np.inf, np.float32), 0, 0, "sim", spec)
    assert scan.ranges.shape == (170,) and scan.angle_min == pytest.approx(-math.pi / 4)


def test_racetrack_is_a_closed_lane_with_room_for_16_cars():
    w = load_world("racetrack")
    assert w.walls.dtype == np.float32 and w.walls.shape[1] == 4
    d = segment_distance(w.centerline[:, 0], w.centerline[:, 1], w.walls)
    assert d.min() > w.lane_width / 2 - 0.05  # no wall crosses the lane anywhere
    assert w.length > 16 * 2.0
    assert 2.0 <= w.lane_width <= 3.0
    poses = w.start_poses(16, np.random.default_rng(0))
    assert poses.shape == (16, 3)
    assert np.allclose(w.progress(*w.centerline_pose(12.3)[:2]), 12.3, atol=1e-3)
    # the loop closes: the pose at s = length is the pose at 0
    assert np.allclose(w.centerline_pose(w.length)[:2], w.centerline_pose(0.0)[:2], atol=1e-6)


def test_intersection_has_open_crossing():
    w = load_world("intersection")
    assert w.centerline is None
    # the crossing centre and the four arms are free of walls
    for x, y in [(0, 0), (5, 0), (-5, 0), (0, 5), (0, -5)]:
        assert segment_distance([x], [y], w.walls)[0] >= w.lane_width / 2 - 1e-6


def test_figure8_crossing_is_open_and_the_lane_closed_elsewhere():
    w = load_world("figure8")
    h = w.lane_width / 2
    # the crossing square and both arms through it are free of walls
    for x, y in [(0, 0), (0.6, 0), (0, -0.6), (3, 0), (-3, 0), (0, 3), (0, -3)]:
        assert segment_distance([x], [y], w.walls)[0] >= h - 1e-3, (x, y)
    assert segment_distance([0], [0], w.walls)[0] >= h * math.sqrt(2) - 0.01  # kerb corners
    # the four kerbs end on the edges of the other arm, within the cut resolution
    ends = w.walls.reshape(-1, 2).astype(np.float64)
    kerb_ends = ends[(np.abs(ends[:, 0]) < h + 0.05) & (np.abs(ends[:, 1]) < h + 0.05)]
    assert len(kerb_ends) == 8  # four wall lines, each cut once: two new ends each
    assert np.allclose(np.abs(kerb_ends), h, atol=0.01)
    # away from the crossing no wall comes closer to the centerline than half a lane
    cl = w.centerline.astype(np.float64)
    away = np.hypot(cl[:, 0], cl[:, 1]) > w.lane_width
    d = segment_distance(cl[away, 0], cl[away, 1], w.walls)
    assert d.min() > h - 0.05
    # a track that does not cross itself is not cut: the racetrack's walls stay whole lines
    rt = load_world("racetrack")
    assert len(rt.walls) == 2 * (len(rt.walls) // 2)


def test_broken_loop_is_rejected(tmp_path):
    from racecav.common.world import WORLDS_DIR
    text = (WORLDS_DIR / "racetrack.toml").read_text().replace("straight = 22.0", "straight = 21.0")
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(ValueError, match="pieces: the loop does not close"):
        load_world(bad)


@pytest.mark.parametrize("name", scenario_names())
def test_shipped_scenarios_validate(name):
    s = load_scenario(name)
    w = load_world(s.world)
    t = s.sample(np.random.default_rng(0))
    if s.traffic is not None:
        assert w.centerline is not None
    elif not s.conflict_timed:
        # timed so that a non-evading ego (holding its start speed) meets the obstacle
        ego = s.ego
        tc = -ego.x / ego.speed
        o = s.obstacles[0]
        dist = o.speed * (tc - o.delay_s)
        ox, oy = o.x + math.cos(math.radians(o.yaw_deg)) * dist, o.y + math.sin(math.radians(o.yaw_deg)) * dist
        assert math.hypot(ox, oy) < 0.3
        assert len(t.obstacles) == len(s.obstacles)
    else:  # conflict-timed: tests/test_scenarios_conflict.py checks that a straight car collides
        assert len(t.obstacles) == len(s.obstacles) and t.obstacles[0].sync is not None


def test_broken_scenario_names_the_field(tmp_path):
    from racecav.common.scenario import SCENARIOS_DIR
    text = (SCENARIOS_DIR / "head-to-head.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("speed = 1.0                # m/s, constant", "speed = -1.0 #"))
    with pytest.raises(ValueError, match=r"obstacles\.0\.speed"):
        load_scenario(bad)
    bad.write_text(text + "\nbogus_field = 3\n")
    with pytest.raises(ValueError, match="bogus_field"):
        load_scenario(bad)
