"""gSDE exploration from a trained policy (``--sde-sample-freq``, training/train.py)."""

from __future__ import annotations

import json

import numpy as np
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
    assert PPO.load(run / "latest.zip", device="cpu").use_sde


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
