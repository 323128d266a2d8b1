"""The MPC-APF baseline in the PyBullet world (in-process): lidar perception finds and tracks what
moves and nothing else; the controller steers around a static obstacle and avoids a crossing one
that a car driving straight would hit."""

from __future__ import annotations

import time

import numpy as np
import pytest

from racecav.common.config import load_config
from racecav.common.lidar import make_scan
from racecav.common.messages import Obstacle, ObstacleStates, VehicleState
from racecav.common.vehicle import load_car

pytest.importorskip("casadi")
pytest.importorskip("pybullet")

STATIC = """
name = "static-obstacle"
world = "intersection"
duration_s = 7.0
[ego]
x = -5.0
y = 0.0
yaw_deg = 0.0
speed = 1.0
[[obstacles]]            # a car parked across the ego's lane, 3 m ahead
x = -2.0
y = 0.05
yaw_deg = 90.0
speed = 0.0
[success]
min_progress_m = 5.0
"""

# A car crossing the ego's road 1 m before the crossing, in plain view (not hidden by a corner):
# a car driving straight at 1 m/s meets it.
CROSSING = """
name = "crossing-obstacle"
world = "intersection"
duration_s = 8.0
[ego]
x = -5.0
y = 0.0
yaw_deg = 0.0
speed = 1.0
[[obstacles]]
x = -1.0
y = -1.1
yaw_deg = 90.0
speed = 0.6
delay_s = 2.0
[success]
min_progress_m = 5.0
"""


@pytest.fixture
def scenario_file(tmp_path):
    def make(text: str, name: str):
        p = tmp_path / f"{name}.toml"
        p.write_text(text)
        return str(p)
    return make


def drive(scenario: str, act, steps: int | None = None):
    """Run ``act(scan, state) -> (a_T, a_delta)`` in a BulletWorld; returns the world's outcome
    and the ego's trajectory (x, y)."""
    from racecav.sim.bullet_world import BulletWorld

    car = load_car()
    with BulletWorld(scenario, car=car) as w:
        w.reset(seed=0)
        steps = steps or int(round(w.scenario.duration_s / car.control_period_s))
        traj = []
        for k in range(steps):
            x, y, yaw, vx = w.agent_state()[0]
            traj.append((x, y))
            stamp = int(round(w.t * 1e9))
            scan = make_scan(w.scan_ranges, stamp, k, "sim", w.spec)
            state = VehicleState(stamp_ns=stamp, seq=k, source="sim", x=x, y=y, yaw=yaw, vx=vx,
                                 steering_angle=float(w.steer[0]))
            if getattr(act, "wants_truth", False):  # oracle: ground-truth obstacles as the sim publishes them
                truth = ObstacleStates(stamp_ns=stamp, seq=k, obstacles=[
                    Obstacle(id=i + 1, x=o[0], y=o[1], yaw=o[2], speed=o[3]) for i, o in enumerate(w.obstacles()[0])])
                a = act(scan, state, truth)
            else:
                a = act(scan, state)
            w.step(np.asarray(a, np.float64))
            if w.collided:
                break
        return {"collided": w.collided, "contact": w.contact_with, "success": bool(w.success()[0]),
                "progress": float(w.progress()[0]), "obstacles": w.obstacles()[0]}, np.array(traj)


def baseline_act(**overrides):
    from racecav.services.baseline.service import MpcApfController

    cfg = load_config().baseline.model_copy(update=overrides)
    ctl = MpcApfController(load_car(), cfg)
    return ctl, lambda scan, state: ctl.act(scan, state, time.monotonic_ns())


def straight(scan, state):
    return 0.24, 0.0  # holds about 1 m/s


def test_baseline_steers_around_a_static_obstacle(scenario_file):
    path = scenario_file(STATIC, "static")
    out, _ = drive(path, straight)
    assert out["collided"] and out["contact"] == "car1"  # it is in the way
    ctl, act = baseline_act()
    out, traj = drive(path, act)
    assert not out["collided"], out
    assert out["success"] and out["progress"] > 5.0
    assert np.abs(traj[:, 1]).max() > 0.3          # it went around, not through
    assert np.abs(traj[-1, 1]) < 0.5                # and came back towards its lane
    st = ctl.stats()
    assert st["solver_failures"] <= 2 and st["iterations_mean"] >= 1, st


def test_baseline_avoids_a_crossing_obstacle(scenario_file):
    path = scenario_file(CROSSING, "crossing")
    out, _ = drive(path, straight)
    assert out["collided"] and out["contact"] == "car1"
    ctl, act = baseline_act()
    out, traj = drive(path, act)
    assert not out["collided"], out
    assert out["success"]
    assert ctl.stats()["episodes"] == 1


def test_perception_tracks_the_mover_and_nothing_else(scenario_file):
    """Ego driving straight past a parked car between curbs: no moving track; a crossing car:
    one moving track with the right velocity."""
    from racecav.services.baseline.perception import Perception

    car = load_car()
    for text, name, n_steps in ((STATIC, "static", 20), (CROSSING, "crossing", 32)):
        per = Perception(car)
        seen = []

        def act(scan, state):
            pc = per.update(scan.ranges, (state.x, state.y, state.yaw), scan.stamp_ns * 1e-9)
            seen.append([(tr.x, tr.y, tr.vx, tr.vy) for tr in pc.obstacles])
            return straight(scan, state)

        out, _ = drive(scenario_file(text, name), act, steps=n_steps)
        if name == "static":
            assert all(not s for s in seen), [s for s in seen if s][:3]
        else:
            # the obstacle starts moving at t = 2 s, at 0.6 m/s along +y
            assert all(not s for s in seen[:20])
            last = seen[-1]
            assert len(last) == 1
            x, y, vx, vy = last[0]
            ox, oy = out["obstacles"][0][:2]
            assert abs(x - ox) < 0.35 and abs(y - oy) < 0.35
            assert abs(vx) < 0.25 and abs(vy - 0.6) < 0.25


def test_oracle_mode_uses_ground_truth(scenario_file):
    """Diagnosis mode: moving obstacles from ObstacleStates instead of the lidar; the crossing car is
    avoided and is in the MPC's obstacle list from the first step it moves."""
    from racecav.services.baseline.service import MpcApfController

    cfg = load_config().baseline.model_copy(update={"obstacles": "oracle"})
    ctl = MpcApfController(load_car(), cfg)
    counts = []

    def act(scan, state, truth):
        out = ctl.act(scan, state, time.monotonic_ns(), truth)
        counts.append(ctl.last["obstacles"])
        return out

    act.wants_truth = True
    out, _ = drive(scenario_file(CROSSING, "crossing"), act)
    assert not out["collided"], out
    assert counts[0] == 1 and min(counts) == 1  # ground truth: always the one car, even hidden or still


def test_solver_exception_is_a_failed_step_not_a_dead_controller():
    """casadi can raise from a solve (seen: stats() after a failed sqpmethod iteration); the
    step falls back to the previous plan, is reported as not ok, and the next step solves again."""
    from racecav.services.baseline.mpc import MpcApf

    cfg = load_config().baseline.model_copy(update={"compile": False})
    mpc = MpcApf(load_car(), cfg)
    z0 = np.array([0.0, 0.0, 0.0, 1.0, 0.0])
    p = mpc.params(z0, (0.0, 0.0, 0.0), 1.0, [], np.zeros((0, 2)))
    first = mpc.solve(p)
    assert first.success and first.throttle > 0
    real = mpc.solver

    def broken(**kw):
        raise RuntimeError("Error in Function::stats for 'mpc' [Sqpmethod]\nmore")

    mpc.solver = broken
    bad = mpc.solve(mpc.params(z0, (0.0, 0.0, 0.0), 1.0, [], np.zeros((0, 2))))
    assert not bad.success and bad.status.startswith("exception: Error in Function::stats")
    assert np.isfinite([bad.throttle, bad.steer_cmd]).all() and bad.x_pred.shape == (cfg.horizon + 1, 5)
    mpc.solver = real
    again = mpc.solve(mpc.params(z0, (0.0, 0.0, 0.0), 1.0, [], np.zeros((0, 2))))
    assert again.success
