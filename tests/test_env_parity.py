"""Parity of the fast backend with the PyBullet reference: same initial state and actions give
the same motion (3 s, within 10 cm), and the same pose gives the same wall ranges (2 cm median)."""

import math

import numpy as np
import pytest

from racecav.common.config import EnvConfig
from racecav.common.vehicle import load_car
from racecav.common.world import load_world
from racecav.sim.fast_world import FastWorld
from racecav.training.env import make_world
from racecav.training.fit_bicycle import (DESIGNED, bullet_rollouts, closed_loop,
                                          designed_actions, fast_rollouts, open_floor_scenario,
                                          position_errors, random_actions, transient_actions)

T = 30  # 3 s of 0.1 s control periods


KINDS = list(DESIGNED)
_mixed = designed_actions


@pytest.fixture(scope="module")
def floor(tmp_path_factory):
    sc = open_floor_scenario(tmp_path_factory.mktemp("floor"))
    return sc, load_world(sc.world), load_car()


def test_motion_parity_designed_sequences(floor):
    """Every designed sequence from rest and from 1.2 m/s, at the obstacle cars' and the agent's
    speed scale (16 rollouts of 3 s): the issue's criterion, every one within 10 cm after 3 s
    (measured, docs/training-env.md: max ~6 cm, median ~2 cm)."""
    sc, world, car = floor
    combos = [(k, v0, s) for k in KINDS for v0 in (0.0, 1.2) for s in (1.0, car.agent_speed_scale)]
    acts = np.stack([_mixed(k) for k, _, _ in combos])
    v0 = np.array([c[1] for c in combos])
    scales = np.array([c[2] for c in combos])
    ref = bullet_rollouts(sc, car, acts, v0, scales)
    got = fast_rollouts(world, car, car.bicycle, acts, v0, scales)
    err = position_errors(got, ref)[:, -1]
    report = dict(zip(combos, err.round(3)))
    travelled = np.hypot(*(ref[:, -1, :2] - ref[:, 0, :2]).T)
    assert np.all(travelled > 1.5)  # the sequences do move the car
    assert np.all(err < 0.10), report
    assert np.median(err) < 0.04, report
    yaw_err = np.abs(np.angle(np.exp(1j * (got[:, -1, 2] - ref[:, -1, 2]))))
    assert np.median(yaw_err) < 0.03 and yaw_err.max() < 0.06, yaw_err.round(3)


def test_motion_parity_random_sequences(floor):
    """Random held actions (not the fit's): median and p90 of the 3 s position error."""
    sc, world, car = floor
    rng = np.random.default_rng(12345)
    acts = random_actions(rng, 16, T)
    v0 = rng.uniform(0.0, 1.5, 16)
    scales = np.where(np.arange(16) % 2 == 0, 1.0, car.agent_speed_scale)
    ref = bullet_rollouts(sc, car, acts, v0, scales)
    got = fast_rollouts(world, car, car.bicycle, acts, v0, scales)
    err = position_errors(got, ref)[:, -1]
    assert np.median(err) < 0.05 and np.percentile(err, 90) < 0.10, err.round(3)


def test_motion_parity_random_headings(floor):
    """PyBullet's grip depends on the heading (world-fixed friction directions): random and
    transient actions from random start headings stay within the same error (the fast model's
    heading term; the previous model, without it, had a p90 of ~16 cm here)."""
    sc, world, car = floor
    rng = np.random.default_rng(4321)
    acts = np.concatenate([random_actions(rng, 8, T), transient_actions(rng, 8, T)])
    v0 = rng.uniform(0.0, 2.0, 16)
    scales = np.where(np.arange(16) % 2 == 0, 1.0, car.agent_speed_scale)
    yaw0 = rng.uniform(-math.pi, math.pi, 16)
    ref = bullet_rollouts(sc, car, acts, v0, scales, yaw0)
    got = fast_rollouts(world, car, car.bicycle, acts, v0, scales, yaw0)
    err = position_errors(got, ref)[:, -1]
    assert np.median(err) < 0.05 and np.percentile(err, 90) < 0.10, err.round(3)


def test_unfitted_model_is_worse(floor):
    """The fit matters: the geometric defaults miss by far more (guards against a fit that
    silently stopped being used)."""
    sc, world, car = floor
    from racecav.common.vehicle import BicycleParams

    acts = np.stack([_mixed(k) for k in KINDS])
    v0, scales = np.zeros(len(KINDS)), np.full(len(KINDS), car.agent_speed_scale)
    ref = bullet_rollouts(sc, car, acts, v0, scales)
    fitted = position_errors(fast_rollouts(world, car, car.bicycle, acts, v0, scales), ref)[:, -1]
    default = position_errors(fast_rollouts(world, car, BicycleParams(), acts, v0, scales), ref)[:, -1]
    assert car.bicycle.fitted
    assert np.mean(fitted) < 0.5 * np.mean(default)


def test_wall_ranges_parity():
    cfg = EnvConfig(backend="bullet", n_obstacles=0)
    bw = make_world(cfg, seed=0)
    fw = FastWorld(n_envs=1, n_obstacles=0, seed=0)
    try:
        bw.reset(seed=0)
        fw.reset(seed=0)
        rng = np.random.default_rng(0)
        world = fw.world
        diffs = []
        for _ in range(24):
            s = rng.uniform(0, world.length)
            x, y, yaw = world.centerline_pose(s)
            off = rng.uniform(-0.6, 0.6)
            x, y = x - off * math.sin(yaw), y + off * math.cos(yaw)
            yaw += rng.uniform(-0.5, 0.5)
            bw.set_state(x=x, y=y, yaw=yaw)
            fw.set_state(0, 0, x=x, y=y, yaw=yaw, v=0.0, w=0.0, delta=0.0)
            rb = bw.scan_ranges
            rf = fw.ranges[0, 0]
            assert np.array_equal(np.isfinite(rb), np.isfinite(rf)) or \
                np.mean(np.isfinite(rb) != np.isfinite(rf)) < 0.02
            both = np.isfinite(rb) & np.isfinite(rf)
            diffs.append(np.abs(rb[both] - rf[both]))
        d = np.concatenate(diffs)
        assert np.median(d) < 0.02 and np.mean(d < 0.02) > 0.95, (np.median(d), np.mean(d < 0.02))
    finally:
        bw.close()


def test_car_ranges_parity():
    """An obstacle car placed ahead of the agent is seen at the same ranges by both backends."""
    bw = make_world(EnvConfig(backend="bullet", n_obstacles=1), seed=0)
    fw = FastWorld(n_envs=1, n_obstacles=1, seed=0)
    try:
        bw.reset(seed=0)
        fw.reset(seed=0)
        diffs = []
        for k, (dx, dy, dyaw) in enumerate([(2.0, 0.0, 0.0), (1.5, 0.4, 0.6), (3.0, -0.5, -1.2),
                                            (1.2, 0.2, math.pi / 2)]):
            ax, ay = 4.0, -0.3
            ox, oy, oyaw = ax + dx, ay + dy, dyaw
            bw.set_state(car=1, x=ox, y=oy, yaw=oyaw)
            bw.set_state(car=0, x=ax, y=ay, yaw=0.0)
            fw.set_state(0, 1, x=ox, y=oy, yaw=oyaw, v=0.0, w=0.0, delta=0.0)
            fw.set_state(0, 0, x=ax, y=ay, yaw=0.0, v=0.0, w=0.0, delta=0.0)
            rb, rf = bw.scan_ranges, fw.ranges[0, 0]
            car_rays = rf < dx + 0.5  # rays that end on the obstacle in the fast world
            assert car_rays.sum() >= 5
            diffs.append(np.abs(rb[car_rays] - rf[car_rays]))
        d = np.concatenate(diffs)
        assert np.median(d) < 0.02 and np.mean(d < 0.02) > 0.9, (np.median(d), np.mean(d < 0.02))
    finally:
        bw.close()


@pytest.mark.parametrize("scale", [1.0, 1.5])
def test_closed_loop_parity(scale):
    """A lidar-feedback controller sees the same scans and drives the same way in both backends:
    it hits the wall at the same control step, having stayed within 10 cm until then."""
    car = load_car()
    tb, tf, hit = closed_loop(car, scale, steps=250)
    assert hit[0] is not None and hit[1] is not None  # this controller does crash, eventually
    assert abs(hit[0] - hit[1]) <= 2
    end = min(hit)
    assert end >= 50  # several seconds of driving before
    assert np.hypot(*(tb[:end, :2] - tf[:end, :2]).T).max() < 0.10
