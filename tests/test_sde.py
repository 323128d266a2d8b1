"""gSDE exploration from a trained policy (``--sde-sample-freq``, training/train.py)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

FLAGS = ["--preset", "fast", "--n-envs", "8", "--n-steps", "16", "--batch-size", "64", "--n-epochs", "2",
         "--checkpoint-every", "128", "--n-obstacles", "2", "--driver", "centerline", "--world", "figure8",
         "--lidar", "wide", "--no-progress"]


def test_a_gsde_run_starts_from_a_policy_with_its_means_and_the_asked_std(tmp_path):
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from racecav.cli import main
    from racecav.common.lidar import VIEWS
    from racecav.training.dagger import mean_action
    from racecav.training.runs import load_run_config
    from racecav.training.train import _ppo_kwargs, calibrate_sde, init_weights, make_venv

    src, run = tmp_path / "src", tmp_path / "sde"
    assert main(["train", "overtake", "--run-dir", str(src), "--steps", "128", *FLAGS]) == 0
    # what train() does for a new gSDE run from a policy
    tc = load_run_config(src)[0].model_copy(update={"sde_sample_freq": 8})
    venv = VecNormalize(make_venv(tc, seed=0))
    b = PPO("MlpPolicy", venv, seed=0, device="cpu", **_ppo_kwargs(tc))
    init_weights(b, src / "latest.zip", 0.3, VIEWS["wide"])
    first = venv.reset()
    calibrate_sde(b, first, 0.3)
    a = PPO.load(src / "latest.zip", device="cpu")
    assert b.use_sde and b.sde_sample_freq == 8 and tuple(b.policy.log_std.shape) == (64, 2)
    obs = torch.as_tensor(np.random.default_rng(1).normal(size=(256, a.observation_space.shape[0])),
                          dtype=torch.float32)
    with torch.no_grad():
        assert torch.allclose(mean_action(a.policy, obs), mean_action(b.policy, obs), atol=1e-6)
        std = b.policy.get_distribution(torch.as_tensor(first)).distribution.stddev
    assert np.allclose(std.pow(2).mean(0).sqrt().numpy(), 0.3, rtol=1e-3), std
    # the command: a run goes on with gSDE and resumes with it
    flags = ["--init-from", str(src / "latest.zip"), "--init-std", "0.3", "--sde-sample-freq", "8", *FLAGS]
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "128", *flags]) == 0
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "256", "--resume", "--no-progress"]) == 0
    assert json.loads((run / "config.json").read_text())["sde_sample_freq"] == 8
    model = PPO.load(run / "latest.zip", device="cpu")
    assert model.use_sde
    # progress.csv's std column is the action std the run explored with (0.3 asked), not SB3's
    # train/std, the noise weights' mean (about 0.3 / |latent| here)
    with (run / "progress.csv").open() as f:
        stds = [float(r["std"]) for r in csv.DictReader(f)]
    weights_mean = float(model.policy.log_std.detach().exp().mean())
    assert len(stds) == 2 and all(0.2 < v < 0.4 for v in stds), stds
    assert weights_mean < 0.15, weights_mean  # so the check above tells the two apart


def test_action_std_is_the_spread_of_the_sampled_gsde_actions():
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    from racecav.training.train import action_std, calibrate_sde

    model = PPO("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=1, seed=0), use_sde=True, device="cpu", seed=0)
    obs = np.random.default_rng(0).normal(size=(16, 3)).astype(np.float32)
    calibrate_sde(model, obs, 0.5)
    policy, o = model.policy, torch.as_tensor(obs)
    draws = []
    with torch.no_grad():
        for _ in range(4000):  # a fresh noise matrix each draw, as every sde_sample_freq steps in a run
            policy.reset_noise(1)
            draws.append(policy.get_distribution(o).get_actions(deterministic=False))
    spread = torch.stack(draws).std(0)  # (obs, action): the std over the noise draws
    measured = float(spread.pow(2).mean(0).sqrt().mean())
    assert action_std(policy, obs) == pytest.approx(measured, rel=0.05)
    assert action_std(policy, obs) == pytest.approx(0.5, rel=1e-3)  # calibrate_sde's definition


def test_a_gsde_policy_into_one_without_needs_an_std(tmp_path):
    from stable_baselines3 import PPO

    from racecav.cli import main

    src = tmp_path / "src"
    assert main(["train", "overtake", "--run-dir", str(src), "--steps", "128", "--sde-sample-freq", "-1", *FLAGS]) == 0
    assert main(["train", "overtake", "--run-dir", str(tmp_path / "a"), "--steps", "0",
                 "--init-from", str(src / "latest.zip"), *FLAGS]) != 0
    assert main(["train", "overtake", "--run-dir", str(tmp_path / "b"), "--steps", "0",
                 "--init-from", str(src / "latest.zip"), "--init-std", "0.3", *FLAGS]) == 0
    # gSDE into gSDE: the source's noise weights go on
    assert main(["train", "overtake", "--run-dir", str(tmp_path / "c"), "--steps", "64", "--sde-sample-freq", "8",
                 "--init-from", str(src / "latest.zip"), "--learning-rate", "1e-12", *FLAGS]) == 0
    a, c = (PPO.load(p / "latest.zip", device="cpu").policy.log_std for p in (src, tmp_path / "c"))
    assert torch.allclose(a, c, atol=1e-6)
