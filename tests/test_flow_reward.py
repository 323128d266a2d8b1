"""The flow reward term (training/flow_reward.py, ``--flow-reward``)."""

from __future__ import annotations

import numpy as np
import pytest

from racecav.common.config import EnvConfig
from racecav.common.scenario import SCENARIOS_DIR


def _flow_term(scenario: str, steer: float, weight: float = 5.0) -> float:
    """The term's sum over a drive at full throttle that steers ``steer`` from 1 s on (the
    same drive with the term off subtracted: the rest of the reward is identical)."""
    from racecav.training.vec_env import FastVecEnv

    totals = []
    for w in (weight, 0.0):
        env = FastVecEnv(config=EnvConfig(n_envs=1, scenarios=str(SCENARIOS_DIR / f"{scenario}.toml"),
                                          scenario_share=1.0, n_obstacles=0, flow_reward=w, lidar="wide"), seed=0)
        env.reset()
        total = 0.0
        for k in range(40):
            _, r, d, _ = env.step(np.array([[1.0, steer if k >= 10 else 0.0]]))
            total += float(r[0])
            if d[0]:
                break
        totals.append(total)
    return totals[0] - totals[1]


@pytest.mark.parametrize("scenario,with_flow", [("left-to-right", -1.0), ("right-to-left", 1.0)])
def test_turning_with_the_crossing_cars_flow_pays_and_against_it_costs(scenario, with_flow):
    # the car from the left moves to the ego's right: a right turn (a_delta < 0) goes with it
    assert _flow_term(scenario, with_flow) > 2.0
    assert _flow_term(scenario, -with_flow) < -2.0


def test_no_term_without_a_crossing_car():
    # head-on: the oncoming car does not cross; off (weight 0) nothing changes either
    assert _flow_term("head-to-head", 1.0) == pytest.approx(0.0, abs=1e-3)
    assert _flow_term("left-to-right", 1.0, weight=0.0) == 0.0


def test_the_gym_env_refuses_the_term():
    # the single-env gym env keeps the paper's reward: the term is the training VecEnv's only
    import gymnasium as gym

    import racecav.training.env  # noqa: F401  (registers racecav/Overtake-v0)

    with pytest.raises(ValueError, match="flow_reward"):
        gym.make("racecav/Overtake-v0", config=EnvConfig(flow_reward=5.0, n_obstacles=0, backend="fast"))
