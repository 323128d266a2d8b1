"""EnvConfig.stand_input: the stand timer after the scans (training/vec_env.FastVecEnv), and a
policy trained without it widened to read it (training/train.init_weights)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from racecav.common.config import EnvConfig, TrainConfig
from racecav.common.vehicle import STAND_SPEED, stood_seconds
from racecav.training.vec_env import FastVecEnv

REPO = Path(__file__).resolve().parents[1]
START = REPO / "training" / "recipes" / "avoid" / "timing" / "step_003006464.zip"


def env_cfg(**kw) -> EnvConfig:
    scen = REPO / "tests" / "data" / "roads_braking_side_approach.toml"
    return EnvConfig(scenarios=str(scen), scenario_share=1.0, lidar="wide", obs_stack=2, obs_stride=4,
                     brake_below=-0.5, heading="reversed", **kw)


def test_stood_seconds_grows_standing_and_resets_moving():
    t = stood_seconds(np.zeros(3), np.array([0.0, STAND_SPEED * 2, -0.01]), 0.1, 3.0)
    assert t.tolist() == [0.1, 0.0, 0.1]
    assert stood_seconds(np.array([2.95]), np.array([0.0]), 0.1, 3.0).tolist() == [3.0]  # capped


def test_the_timer_is_the_last_input_and_follows_the_ego():
    env = FastVecEnv(n_envs=2, config=env_cfg(stand_input=3.0), seed=0)
    assert env.observation_space.shape == (2 * 169 + 1,)
    assert env.observation_space.high[-1] == 3.0
    obs = env.reset()
    assert obs.shape == (2, 339) and (obs[:, -1] == 0).all()
    brake = np.tile([-1.0, 0.0], (2, 1)).astype(np.float32)
    go = np.tile([1.0, 0.0], (2, 1)).astype(np.float32)
    for _ in range(5):  # off at full throttle, then brake to a stop and stand
        obs, *_ = env.step(go)
    assert (obs[:, -1] == 0).all()
    v = lambda: np.concatenate([w.v[:, 0] for w in env.worlds])  # noqa: E731
    for _ in range(60):
        obs, *_ = env.step(brake)
    assert (np.abs(v()) < STAND_SPEED).all() and (obs[:, -1] > 0.5).all()
    assert (obs[:, :-1] == env.stacked_view(2, 4)).all()  # the scans as before
    for _ in range(3):
        obs, *_ = env.step(go)
    assert (obs[:, -1] == 0).all()
    plain = FastVecEnv(n_envs=2, config=env_cfg(), seed=0)
    assert plain.reset().shape == (2, 338)


@pytest.mark.skipif(not START.is_file(), reason="the recipe's committed timing weights")
def test_a_policy_without_the_timer_starts_reading_it_with_zero_weight(tmp_path):
    """init_weights widens the first layer with a zero column, init_normalization adds 0 +- 1:
    the widened model acts as the old one whatever the timer says."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from racecav.common.lidar import VIEWS
    from racecav.training.policy_io import policy_from_checkpoint
    from racecav.training.train import _ppo_kwargs, init_normalization, init_weights

    torch.set_num_threads(1)
    tc = TrainConfig(stage="dagger", init_from=str(START), env=env_cfg(stand_input=3.0), n_steps=8, batch_size=16)
    fast = FastVecEnv(n_envs=2, config=tc.env, seed=0)
    venv = init_normalization(VecNormalize(fast, norm_obs=True, norm_reward=False), tc)
    model = PPO("MlpPolicy", venv, device="cpu", **_ppo_kwargs(tc))
    init_weights(model, START, None, VIEWS["wide"], 4)
    old = policy_from_checkpoint(START, 2, -0.5, "wide", 4)
    obs = fast.reset()
    for t in (0.0, 1.5, 3.0):
        x = obs.copy()
        x[:, -1] = t
        new, _ = model.predict(venv.normalize_obs(x), deterministic=True)
        assert np.allclose(np.clip(new, -1, 1), old(obs[:, :-1]), atol=1e-5)
    assert venv.obs_rms.mean[-1] == 0.0 and venv.obs_rms.var[-1] == 1.0


def test_the_single_env_refuses_the_timer():
    from racecav.training.env import OvertakeEnv

    with pytest.raises(ValueError, match="stand_input"):
        OvertakeEnv(config=env_cfg(stand_input=3.0))


def test_a_policy_with_the_timer_loads_and_the_services_refuse_it_clearly():
    from racecav.common.config import Config
    from racecav.common.policy import NumpyPolicy
    from racecav.services.policy.service import PolicyService

    rng = np.random.default_rng(0)
    arrays = {"w0": rng.normal(size=(339, 8)), "b0": np.zeros(8), "w1": rng.normal(size=(8, 8)), "b1": np.zeros(8),
              "w2": rng.normal(size=(8, 2)), "b2": np.zeros(2)}
    meta = {"obs_stack": 2, "obs_stride": 4, "lidar": "wide", "brake_below": -0.5}
    with pytest.raises(ValueError, match="obs_stack 2 does not divide"):
        NumpyPolicy(arrays, meta)
    pol = NumpyPolicy(arrays, {**meta, "stand_input": 3.0})
    assert pol(np.ones(339)).shape == (2,)
    with pytest.raises(ValueError, match="stand timer"):
        PolicyService(Config(), policy=pol)
