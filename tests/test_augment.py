"""PPO on its rollouts seen in a mirror (training/augment.py, ``--mirror-augment``)."""

from __future__ import annotations

import json

import numpy as np
import torch

from racecav.training.mirror import mirror_scans


def test_the_reflected_half_of_the_buffer_is_the_rollout_in_a_mirror(tmp_path):
    """After a rollout the buffer holds the reflected samples beside the real ones: the raw scans
    reflected, the steering negated, the same returns and advantages, and the policy's own
    log-probability of each reflected action (PPO's ratio starts at 1); the update restores the
    buffer's size for the next rollout."""
    from stable_baselines3.common.vec_env import VecNormalize

    from racecav.common.config import EnvConfig, TrainConfig
    from racecav.training.augment import augment_buffer, mirror_augmented_ppo
    from racecav.training.train import make_venv

    tc = TrainConfig(n_steps=8, batch_size=32, n_epochs=1, env=EnvConfig(n_envs=4, n_obstacles=2, world="figure8",
                                                                      driver="centerline", obs_stack=2, lidar="wide"))
    venv = VecNormalize(make_venv(tc, seed=3))
    model = mirror_augmented_ppo()("MlpPolicy", venv, n_steps=8, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.mirror_obs_stack = 2
    model.learn(32)  # one rollout and update, so the statistics are not the identity
    buf = model.rollout_buffer
    assert buf.n_envs == 4
    _, callback = model._setup_learn(8, reset_num_timesteps=False)
    assert model.collect_rollouts(model.env, callback, buf, n_rollout_steps=8)
    real = {k: getattr(buf, k).copy() for k in ("observations", "actions", "returns", "advantages")}
    assert augment_buffer(model, 2) == 4 and buf.n_envs == 8
    rms, eps = venv.obs_rms, venv.epsilon
    raw = real["observations"] * np.sqrt(rms.var + eps) + rms.mean
    mirrored = buf.observations[:, 4:] * np.sqrt(rms.var + eps) + rms.mean
    inside = ((np.abs(buf.observations[:, 4:]) < venv.clip_obs)
              & (np.abs(mirror_scans(real["observations"], 2)) < venv.clip_obs))
    assert inside.mean() > 0.9  # (VecNormalize clips at +-10: a clipped value has no raw value)
    assert np.allclose(mirrored[inside], mirror_scans(raw, 2)[inside], atol=1e-3)
    assert np.array_equal(buf.actions[:, 4:, 0], real["actions"][..., 0])
    assert np.array_equal(buf.actions[:, 4:, 1], -real["actions"][..., 1])
    assert np.array_equal(buf.returns[:, 4:], real["returns"]) and np.array_equal(buf.advantages[:, 4:], real["advantages"])
    with torch.no_grad():
        _, logp, _ = model.policy.evaluate_actions(torch.as_tensor(buf.observations[:, 4:].reshape(32, -1)),
                                                   torch.as_tensor(buf.actions[:, 4:].reshape(32, 2)))
    assert np.allclose(buf.log_probs[:, 4:].reshape(-1), logp.numpy(), atol=1e-5)
    buf.n_envs = 4  # (what MirrorAugmentedPPO.train does after its update)
    model.learn(64, reset_num_timesteps=False)  # rollouts and augmented updates run ...
    assert model.rollout_buffer.n_envs == 4     # ... and each rollout has the env's size


def test_mirror_augmented_run_records_the_flag_and_resumes(tmp_path):
    from racecav.cli import main

    flags = ["--preset", "fast", "--n-envs", "8", "--n-steps", "16", "--batch-size", "64", "--n-epochs", "2",
             "--checkpoint-every", "128", "--n-obstacles", "2", "--driver", "centerline", "--world", "figure8",
             "--obs-stack", "2", "--lidar", "wide", "--no-progress"]
    run = tmp_path / "aug"
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "128", "--mirror-augment", *flags]) == 0
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "256", "--resume", "--no-progress"]) == 0
    assert json.loads((run / "config.json").read_text())["mirror_augment"] is True
    rows = (run / "progress.csv").read_text().splitlines()
    assert rows[-1].split(",")[0] == "256"
