"""The reward terms of ``racecav train overtake --hold-heading W`` and ``--hold-track W``
(training/hold_heading.py) and ``--proximity-penalty W`` (training/proximity.py)."""

from __future__ import annotations

import numpy as np
import pytest

from racecav.common.config import EnvConfig
from racecav.common.scenario import SCENARIOS_DIR
from racecav.training.env import OvertakeEnv
from racecav.training.vec_env import FastVecEnv

W = 10.0


def _env(hold: float) -> FastVecEnv:
    # the paper's left-to-right: the corners hide the crossing car for the first metres
    return FastVecEnv(config=EnvConfig(n_envs=8, scenarios=str(SCENARIOS_DIR / "left-to-right.toml"),
                                       scenario_share=1.0, n_obstacles=0, lidar="wide", hold_heading=hold), seed=4)


def test_heading_error_is_charged_until_a_car_has_been_in_view():
    """Against the same worlds without the term: the reward differs by -W x |heading error| at
    each step before the ego's scan first shows the car (FastWorld.seen_by_agent), by nothing
    from then on, even once the car is out of view again; a new episode starts unseen again."""
    env, ref = _env(W), _env(0.0)
    env.reset(), ref.reset()
    (w,) = env.worlds
    # rows 0-3 hold their road, rows 4-7 swerve left and back before the car can be seen
    a = np.tile(np.array([1.0, 0.0], np.float32), (8, 1))
    charged = np.zeros(8)
    seen_then_hidden = 0
    latched = np.zeros(8, dtype=bool)
    for k in range(40):
        a[4:, 1] = 1.0 if k < 3 else -1.0 if k < 6 else 0.0
        _, r, d, _ = env.step(a)
        _, r0, d0, _ = ref.step(a)
        assert np.array_equal(d, d0)
        if d.any():  # the first episode ends (past the crossing): new episodes start unseen
            assert k > 20 and not env.hold_heading.seen[d].any()
            break
        err = np.abs(np.angle(np.exp(1j * (w.yaw[:, 0] - w.start_pose[:, 2]))))
        seen_now = w.seen_by_agent(np.arange(8))[:, 0]
        latched |= seen_now
        assert np.array_equal(env.hold_heading.seen, latched)
        expected = np.where(latched, 0.0, -W * err)
        assert np.allclose(r - r0, expected, atol=1e-4)
        charged += r - r0
        seen_then_hidden += int((latched & ~seen_now).sum())
    assert latched.all()
    assert (charged[4:] < -1.0).all() and (charged[:4] > -0.5).all()
    assert seen_then_hidden > 0
    env.close(), ref.close()


def test_the_term_is_refused_outside_the_fast_vec_env():
    with pytest.raises(ValueError, match="hold_heading"):
        OvertakeEnv(config=EnvConfig(hold_heading=1.0))
    with pytest.raises(ValueError, match="hold_track"):
        OvertakeEnv(config=EnvConfig(hold_track=1.0))
    with pytest.raises(ValueError, match="hold_track: .*drop hold_heading"):
        EnvConfig(hold_track=1.0, hold_heading=1.0)


def _ghost(w) -> np.ndarray:
    """(N, 3) each ego moved onto its road's line at its progress, with the road's heading."""
    x0, y0, yaw0 = w.start_pose.T
    s = w.progress()
    return np.stack([x0 + s * np.cos(yaw0), y0 + s * np.sin(yaw0), yaw0], axis=1)


def test_seen_from_a_pose_is_the_view_of_the_agent_moved_there():
    """FastWorld.seen_by_agent(envs, pose) equals the plain call on a copy of the world whose
    agent was moved to ``pose`` (set_state), and leaves the world as it was."""
    import copy

    env = _env(0.0)
    env.reset()
    (w,) = env.worlds
    a = np.tile(np.array([1.0, 0.0], np.float32), (8, 1))
    compared = differs = 0
    for k in range(25):
        a[4:, 1] = 0.5 if k < 4 else -0.5 if k < 8 else 0.0  # rows 4-7 drift left: another view
        env.step(a)
        envs = np.arange(8)
        pose = _ghost(w)
        before = (w.x.copy(), w.ranges.copy(), w.corners.copy())
        got = w.seen_by_agent(envs, pose=pose)
        assert np.array_equal(w.x, before[0]) and np.array_equal(w.ranges, before[1]) and np.array_equal(w.corners, before[2])
        moved = copy.deepcopy(w)
        for n in envs:
            moved.set_state(int(n), 0, x=pose[n, 0], y=pose[n, 1], yaw=pose[n, 2])
        assert np.array_equal(got, moved.seen_by_agent(envs))
        assert np.array_equal(w.seen_by_agent(envs, pose=w.agent_state()[:, :3]), w.seen_by_agent(envs))
        compared += got.any(axis=1).sum()
        differs += int((got != w.seen_by_agent(envs)).any(axis=1).sum())
    assert compared > 0 and differs > 0
    env.close()


def test_hold_track_charges_any_departure_from_a_straight_pass_until_a_straight_ego_would_see():
    """--hold-track W: against the same worlds without it, the reward differs by
    -W x (|lateral offset| + |heading error| + (1 - T)) until a car is in the ghost's view (the ego
    moved onto its road), by nothing after; a drift that shows the car early does not end it."""
    mk = lambda w: FastVecEnv(config=EnvConfig(n_envs=8, scenarios=str(SCENARIOS_DIR / "left-to-right.toml"),
                                               scenario_share=1.0, n_obstacles=0, lidar="wide", hold_track=w), seed=4)
    env, ref = mk(W), mk(0.0)
    env.reset(), ref.reset()
    (w,) = env.worlds
    # rows 0-3 hold their road at full throttle; rows 4-7 drift right at 0.7 throttle (and see
    # past the corner a step before a straight ego at their progress would)
    a = np.tile(np.array([1.0, 0.0], np.float32), (8, 1))
    latched = np.zeros(8, dtype=bool)
    own_first = 0  # steps where a drifting ego sees the car and the ghost does not yet
    for k in range(40):
        a[4:] = (0.7, -0.5 if k < 4 else 0.5 if k < 8 else 0.0)
        _, r, d, _ = env.step(a)
        _, r0, d0, _ = ref.step(a)
        assert np.array_equal(d, d0)
        if d.any():
            assert not env.hold_heading.seen[d].any()
            break
        x0, y0, yaw0 = w.start_pose.T
        lat = np.abs(-(w.x[:, 0] - x0) * np.sin(yaw0) + (w.y[:, 0] - y0) * np.cos(yaw0))
        head = np.abs(np.angle(np.exp(1j * (w.yaw[:, 0] - yaw0))))
        ghost_sees = w.seen_by_agent(np.arange(8), pose=_ghost(w))[:, 0]
        own_first += int((w.seen_by_agent(np.arange(8))[:, 0] & ~(latched | ghost_sees))[4:].sum())
        latched |= ghost_sees
        assert np.array_equal(env.hold_heading.seen, latched)
        expected = np.where(latched, 0.0, -W * (lat + head + (1.0 - np.clip(a[:, 0], 0, 1))))
        assert np.allclose(r - r0, expected, atol=1e-3)
    assert latched[:4].all() and own_first > 0
    env.close(), ref.close()


def test_proximity_penalty_is_the_margin_to_the_nearest_car_within_reach():
    """--proximity-penalty W: against the same worlds without it, the reward differs by
    -W x (NEAR_M - d) at the steps where the nearest car's centre is d < NEAR_M away, by nothing
    elsewhere; a straight ego meets the paper's crossing car head-on, so both cases occur."""
    from racecav.training.proximity import NEAR_M

    def env(w):
        return FastVecEnv(config=EnvConfig(n_envs=4, scenarios=str(SCENARIOS_DIR / "left-to-right.toml"),
                                           scenario_share=1.0, n_obstacles=0, lidar="wide", proximity_penalty=w), seed=4)

    e, ref = env(W), env(0.0)
    e.reset(), ref.reset()
    (w,) = e.worlds
    a = np.tile(np.array([0.22, 0.0], np.float32), (4, 1))  # 1 m/s: on a collision course (the paper's timing)
    near = far = 0
    for _ in range(60):
        _, r, d, _ = e.step(a)
        _, r0, _, _ = ref.step(a)
        if d.any():
            break
        dist = np.hypot(w.x[:, 1] - w.x[:, 0], w.y[:, 1] - w.y[:, 0])
        assert np.allclose(r - r0, -W * np.clip(NEAR_M - dist, 0, None), atol=1e-4)
        near += int((dist < NEAR_M).sum())
        far += int((dist >= NEAR_M).sum())
    assert d.any() and near > 0 and far > 0
    e.close(), ref.close()
