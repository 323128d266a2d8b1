"""The world contract (racecav.sim.contract.World): both backends answer the same calls with the
same shapes and meanings, on a traffic episode and on a scenario episode."""

from __future__ import annotations

import numpy as np
import pytest

from racecav.common.scenario import load_scenario
from racecav.sim.bullet_world import BulletWorld
from racecav.sim.contract import World
from racecav.sim.fast_world import FastWorld


def _backends(kind: str):
    if kind == "traffic":
        return [BulletWorld("racetrack", n_obstacles=3, seed=1), FastWorld(n_envs=1, n_obstacles=3, seed=1)]
    sc = load_scenario("conflict-head-to-head")
    return [BulletWorld(sc), FastWorld(n_envs=1, scenarios=[sc], seed=1)]


@pytest.mark.parametrize("kind", ["traffic", "scenario"])
def test_both_backends_keep_the_contract(kind):
    for w in _backends(kind):
        try:
            assert isinstance(w, World), type(w).__name__
            w.seed(3)
            obs = w.reset()
            n, r = w.n_envs, w.spec.n_rays
            assert obs.shape == (n, r) and obs.dtype == np.float32
            assert w.agent_state().shape == (n, 4)
            assert w.time.shape == (n,) and np.all(w.time == 0.0)
            assert w.time_limit.shape == (n,)
            if kind == "scenario":
                assert np.all(w.time_limit == 14.0)
            obst = w.obstacles()
            assert obst.ndim == 3 and obst.shape[0] == n and obst.shape[2] == 4
            assert obst.shape[1] == (3 if kind == "traffic" else 1)
            x0 = w.agent_state()[0].copy()
            for _ in range(5):
                obs, (thr, a_d), collided, info = w.step(np.tile([1.0, 0.3], (n, 1)))
            assert obs.shape == (n, r) and thr.shape == (n,) and a_d.shape == (n,) and collided.shape == (n,)
            assert np.allclose(thr, 1.0) and np.allclose(a_d, 0.3)
            assert np.allclose(w.time, 5 * w.control_period)
            assert w.progress().shape == (n,) and w.progress()[0] > 0.1  # it drove forward
            assert w.success().dtype == bool and w.contact().dtype == bool
            assert w.agent_state()[0, 3] > x0[3]  # faster at full throttle
            w.set_state(0, 0, x=float(x0[0]), y=float(x0[1]), yaw=float(x0[2]), v=0.5)
            assert np.allclose(w.agent_state()[0, :3], x0[:3], atol=1e-6)
            assert abs(w.agent_state()[0, 3] - 0.5) < 0.05
            # the brake action: from full speed, braking stops the car where coasting does not
            ends = []
            for brake in (False, True):
                w.set_state(0, 0, x=float(x0[0]), y=float(x0[1]), yaw=float(x0[2]), v=0.0)
                for _ in range(12):
                    w.step(np.tile([1.0, 0.0], (n, 1)))
                for _ in range(5):
                    w.step(np.tile([-1.0, 0.0], (n, 1)), brake=np.full(n, brake))
                ends.append(w.agent_state()[0, 3])
            assert ends[0] > 1.0 and ends[1] < 0.2, ends
        finally:
            close = getattr(w, "close", None)
            if close:
                close()


def test_braking_is_the_same_in_both_backends():
    """The brake (wheel speed target 0): PyBullet's locked wheels skid at about mu g with the
    heading held whatever the steering; the fast world's brake_decel and skid reproduce it."""
    sc = load_scenario("conflict-right-to-left")
    ends = {}
    for w in (BulletWorld(sc), FastWorld(n_envs=1, scenarios=[sc], seed=1)):
        try:
            w.seed(0)
            w.reset()
            for _ in range(12):  # ~2 m/s
                w.step(np.array([[1.0, 0.0]]))
            s0 = w.agent_state()[0].copy()
            for _ in range(4):  # brake, steering fully left
                w.step(np.array([[-1.0, 1.0]]), brake=np.array([True]))
            s = w.agent_state()[0]
            ends[type(w).__name__] = (float(np.hypot(*(s[:2] - s0[:2]))), float(s[2] - s0[2]), float(s[3]), float(s0[3]))
        finally:
            getattr(w, "close", lambda: None)()
    (db, yb, vb, v0b), (df, yf, vf, v0f) = ends["BulletWorld"], ends["FastWorld"]
    assert v0b > 1.8 and v0f > 1.8 and abs(vb) < 0.05 and abs(vf) < 0.05, ends  # stopped
    assert 0.1 < db < 0.3 and abs(df - db) < 0.05, ends  # stopping distance
    assert abs(yb) < 0.02 and abs(yf) < 0.02, ends  # the steering does not turn a skidding car
