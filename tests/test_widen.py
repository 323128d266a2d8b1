"""A wider policy started from a trained 2 x 64 one (``--hidden``, training/widen.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
# row 31 of the ablation (gSDE, wide view, 2 scans): the avoid policy shipped on 2026-12-02
SOURCE = ROOT / "training/checkpoints/avoid-gsde-flow120/checkpoints/step_005005312.zip"
FLAGS = ["--preset", "fast", "--n-envs", "8", "--n-steps", "16", "--batch-size", "64", "--n-epochs", "2",
         "--checkpoint-every", "128", "--n-obstacles", "2", "--driver", "centerline", "--world", "figure8",
         "--lidar", "wide", "--obs-stack", "2", "--sde-sample-freq", "32", "--no-progress"]


def test_a_widened_policy_computes_what_the_narrow_one_did(tmp_path):
    """What train() does for a new run with --hidden 128 from a 2 x 64 gSDE checkpoint: the same
    action means, values and action noise; the numpy path of the wider actor equals SB3."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from racecav.common.config import EnvConfig, TrainConfig
    from racecav.common.lidar import VIEWS
    from racecav.common.policy import NumpyPolicy, policy_arrays_from_sb3
    from racecav.training.dagger import mean_action
    from racecav.training.train import _ppo_kwargs, init_weights, make_venv

    torch.set_num_threads(1)
    tc = TrainConfig(hidden=128, sde_sample_freq=32, env=EnvConfig(n_envs=2, n_obstacles=2, world="figure8",
                                                                    lidar="wide", obs_stack=2))
    wide = PPO("MlpPolicy", VecNormalize(make_venv(tc, seed=0)), seed=0, device="cpu", **_ppo_kwargs(tc))
    init_weights(wide, SOURCE, view=VIEWS["wide"])
    narrow = PPO.load(SOURCE, device="cpu")
    assert tuple(wide.policy.log_std.shape) == (128, 2)
    assert tuple(wide.policy.mlp_extractor.value_net[2].weight.shape) == (128, 128)
    obs = torch.as_tensor(np.random.default_rng(1).normal(size=(512, 338)), dtype=torch.float32)
    with torch.no_grad():
        assert torch.allclose(mean_action(wide.policy, obs), mean_action(narrow.policy, obs), atol=1e-5)
        assert torch.allclose(wide.policy.predict_values(obs), narrow.policy.predict_values(obs), atol=1e-4)
        std_w = wide.policy.get_distribution(obs).distribution.stddev
        std_n = narrow.policy.get_distribution(obs).distribution.stddev
    np.testing.assert_allclose(std_w.numpy(), std_n.numpy(), rtol=1e-4)
    # the numpy path and the fused kernel of the wider actor (no normalisation: inputs as given)
    from racecav.common.lidar import LidarSpec
    from racecav.services.policy.fused import FusedPolicy

    pol = NumpyPolicy(policy_arrays_from_sb3(wide), {})
    want = np.clip(mean_action(wide.policy, obs[:32]).detach().numpy(), -1, 1)
    np.testing.assert_allclose(np.stack([pol(o) for o in obs[:32].numpy()]), want, atol=1e-5)
    ranges = torch.as_tensor(np.random.default_rng(2).uniform(0.1, 10.0, (32, 338)), dtype=torch.float32)
    fused = FusedPolicy(pol, LidarSpec(range_min=0.05, range_max=12.0))  # limits that clip none of these
    np.testing.assert_allclose(np.array([fused(r) for r in ranges.numpy()]),
                               np.clip(mean_action(wide.policy, ranges).detach().numpy(), -1, 1), atol=1e-5)


def test_widen_refuses_a_narrower_width():
    from stable_baselines3 import PPO

    from racecav.training.widen import widen

    state = PPO.load(SOURCE, device="cpu").policy.state_dict()
    with pytest.raises(ValueError, match="narrower"):
        widen(state, 32)
    assert widen(state, 64)["mlp_extractor.policy_net.0.weight"].equal(state["mlp_extractor.policy_net.0.weight"])


def test_a_wider_run_trains_its_copies_apart_and_resumes(tmp_path):
    """The command: --hidden is recorded, the run resumes at its width, and training separates
    each copied unit from its original (the random split of the outgoing weights)."""
    from stable_baselines3 import PPO

    from racecav.cli import main

    run = tmp_path / "wide"
    flags = ["--init-from", str(SOURCE), "--hidden", "128", *FLAGS]
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "128", *flags]) == 0
    # Adam's first steps are nearly sign steps, the same for a unit and its copy: a few more updates
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "1024", "--resume", "--no-progress"]) == 0
    assert json.loads((run / "config.json").read_text())["hidden"] == 128
    sd = PPO.load(run / "latest.zip", device="cpu").policy.state_dict()
    for k in ("mlp_extractor.policy_net.0.weight", "mlp_extractor.policy_net.2.weight"):
        w = sd[k].numpy()
        assert w.shape[0] == 128 and len(np.unique(w, axis=0)) == 128, k
