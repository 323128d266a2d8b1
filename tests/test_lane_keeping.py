"""The lane-keeping reward term (EnvConfig.lane_keeping, training/lane_keeping.py).

It charges steering away from plain tracking exactly while tracking would pass free, so on a
straight drive it turns off one look-ahead before the contact, and never on a drive that passes.
"""

from __future__ import annotations

import numpy as np
import pytest

from racecav.common.config import EnvConfig
from racecav.common.scenario import SCENARIOS_DIR
from racecav.training.env import OvertakeEnv
from racecav.training.lane_keeping import LaneKeeping
from racecav.training.vec_env import FastVecEnv

WEIGHT, HORIZON_S = 2.0, 1.2


def _env(name: str, lane_keeping: float = WEIGHT) -> FastVecEnv:
    cfg = EnvConfig(scenarios=str(SCENARIOS_DIR / f"{name}.toml"), scenario_share=1.0, lane_keeping=lane_keeping,
                    lane_keeping_horizon_s=HORIZON_S)
    return FastVecEnv(n_envs=4, config=cfg, seed=3)


def _drive_tracking(name: str):
    """Drive the tracking action; per step: the term's "free" mask, and the step of the contact."""
    env = _env(name)
    env.reset()
    (_, check), = env.lane_keeping.checks
    free, contact = [], np.full(env.num_envs, -1)
    for step in range(200):
        free.append(check.scores()[:, 0] > LaneKeeping.CONTACT)
        a = np.stack([np.ones(env.num_envs), check.first_track], 1)
        _, _, done, infos = env.step(a)
        for i in np.flatnonzero(done & (contact < 0)):
            contact[i] = step if not infos[i]["TimeLimit.truncated"] else 10**6
        if (contact >= 0).all():
            break
    return np.array(free), contact


def test_term_is_off_one_horizon_before_a_straight_contact():
    free, contact = _drive_tracking("conflict-left-to-right")
    h = round(HORIZON_S / 0.1)
    for i, c in enumerate(contact):
        assert 0 < c < 10**6, "the conflict-timed car meets a straight ego"
        closed = np.flatnonzero(~free[:c + 1, i])
        # the look-ahead is an exact copy of the world: it sees the contact h steps ahead, not earlier
        assert closed.size and closed[0] in (c - h + 1, c - h), (closed[:3], c)
        assert free[:closed[0], i].all()


def test_term_never_closes_on_a_drive_that_passes():
    free, contact = _drive_tracking("left-to-right")  # the paper's timing: a fast straight ego passes
    assert (contact == 10**6).all()
    assert free.all()


def test_term_is_the_weighted_steering_deviation_while_free():
    a_env, b_env = _env("left-to-right"), _env("left-to-right", lane_keeping=0.0)
    a_env.reset(), b_env.reset()
    (_, check), = a_env.lane_keeping.checks
    rng = np.random.default_rng(0)
    for _ in range(5):
        check.scores()
        track = check.first_track.copy()
        act = np.stack([np.ones(4), rng.uniform(-1, 1, 4)], 1)
        _, ra, _, _ = a_env.step(act)
        _, rb, _, _ = b_env.step(act)
        np.testing.assert_allclose(ra - rb, -WEIGHT * np.abs(act[:, 1] - track), atol=1e-4)


def test_single_env_refuses_the_term():
    with pytest.raises(ValueError, match="lane_keeping"):
        OvertakeEnv(config=EnvConfig(lane_keeping=1.0))
