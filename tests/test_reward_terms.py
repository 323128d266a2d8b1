"""The reward terms of ``racecav train overtake --hold-heading W`` (training/hold_heading.py) and
``--proximity-penalty W`` (training/proximity.py)."""

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
