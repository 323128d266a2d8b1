"""The privileged critic (``racecav train overtake ... --privileged-critic``, training/privileged.py):
the critic reads the other cars' states, the actor (the policy that ships) the scans only."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch

from racecav.common.config import EnvConfig
from racecav.common.scenario import SCENARIOS_DIR
from racecav.training.privileged import ABSENT, N_PRIVILEGED, NEAREST, POS_SCALE, SPEED_SCALE, privileged_features
from racecav.training.vec_env import FastVecEnv

FLAGS = ["--preset", "fast", "--n-envs", "8", "--n-steps", "16", "--batch-size", "64", "--n-epochs", "2",
         "--checkpoint-every", "128", "--n-obstacles", "2", "--driver", "centerline", "--world", "figure8",
         "--lidar", "wide", "--obs-stack", "2", "--scenarios", str(SCENARIOS_DIR / "left-to-right.toml"),
         "--scenario-share", "0.5", "--no-progress"]


def _env(privileged: bool) -> FastVecEnv:
    cfg = EnvConfig(n_envs=4, scenarios=str(SCENARIOS_DIR / "left-to-right.toml"), scenario_share=1.0,
                    n_obstacles=0, lidar="wide", obs_stack=2)
    return FastVecEnv(config=cfg, seed=3, privileged=privileged)


def test_features_are_the_crossing_car_in_the_egos_frame_and_the_scans_are_unchanged():
    """The paper's left-to-right: the crossing car, 4 m ahead and 4 m to the left of the ego at
    the start, heading south at 1 m/s, is the first car of the features; the other slots are
    absent. The scans are those of the same worlds without the features, step after step."""
    env, ref = _env(True), _env(False)
    obs, obs0 = env.reset(), ref.reset()
    n_scan = obs0.shape[1]
    assert obs.shape == (4, n_scan + N_PRIVILEGED) and env.observation_space.shape == (n_scan + N_PRIVILEGED,)
    (w,) = env.worlds
    a = np.tile(np.array([0.5, 0.1], np.float32), (4, 1))
    south = np.zeros(4, bool)
    for step in range(30):
        assert np.array_equal(obs[:, :n_scan], obs0)
        f = obs[:, n_scan:]
        assert np.array_equal(f, privileged_features(w))
        # the reference computation, car by car, in the ego's frame
        c, s = np.cos(w.yaw[:, 0]), np.sin(w.yaw[:, 0])
        dx, dy = w.x[:, 1] - w.x[:, 0], w.y[:, 1] - w.y[:, 0]
        vx = w.v[:, 1] * np.cos(w.yaw[:, 1]) - w.v[:, 0] * c
        vy = w.v[:, 1] * np.sin(w.yaw[:, 1]) - w.v[:, 0] * s
        want = np.stack([(c * dx + s * dy) / POS_SCALE, (-s * dx + c * dy) / POS_SCALE,
                         (c * vx + s * vy) / SPEED_SCALE, (-s * vx + c * vy) / SPEED_SCALE], axis=1)
        assert np.allclose(f[:, 2:6], want, atol=1e-5)
        assert np.allclose(f[:, 0], w.v[:, 0] / SPEED_SCALE, atol=1e-6)
        assert np.all(f[:, 6:].reshape(4, NEAREST - 1, 4) == np.asarray(ABSENT, np.float32))
        if step == 0:  # ahead and to the left
            assert np.all(f[:, 2] > 3.5 / POS_SCALE) and np.all(f[:, 3] > 3.5 / POS_SCALE)
        south |= f[:, 5] < -0.8 / SPEED_SCALE  # once it moves: towards the ego's road
        obs, _, done, info = env.step(a)
        obs0, _, done0, _ = ref.step(a)
        assert np.array_equal(done, done0)
        for i in np.flatnonzero(done):
            assert info[i]["terminal_observation"].shape == (n_scan + N_PRIVILEGED,)
    assert south.all()


def test_the_actor_reads_the_scans_only_and_starts_as_its_source(tmp_path):
    """A run with --privileged-critic from a plain run's policy: at the start the actor and the
    critic are the source's whatever the privileged inputs are; after training the actor still
    ignores them, the critic does not; its checkpoint exports (and is evaluated) as the SB3
    actor on the scans alone, and the run resumes."""
    from stable_baselines3 import PPO

    from racecav.cli import main
    from racecav.training.select import checkpoint_policy

    src, run, still = tmp_path / "src", tmp_path / "priv", tmp_path / "still"
    assert main(["train", "overtake", "--run-dir", str(src), "--steps", "128", *FLAGS]) == 0
    flags = ["--init-from", str(src / "latest.zip"), "--privileged-critic", *FLAGS]
    # one rollout at a learning rate of ~0: the model as it starts
    assert main(["train", "overtake", "--run-dir", str(still), "--steps", "128", "--lr", "1e-12", *flags]) == 0
    a, b = (PPO.load(p / "latest.zip", device="cpu").policy for p in (src, still))
    n_scan = a.observation_space.shape[0]
    rng = np.random.default_rng(0)
    obs = torch.as_tensor(rng.normal(size=(64, n_scan)), dtype=torch.float32)
    priv = torch.as_tensor(rng.normal(size=(64, N_PRIVILEGED)), dtype=torch.float32)
    full = torch.cat([obs, priv], 1)
    with torch.no_grad():
        assert torch.allclose(a.get_distribution(obs).distribution.mean, b.get_distribution(full).distribution.mean)
        assert torch.allclose(a.predict_values(obs), b.predict_values(full), atol=1e-6)

    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "128", *flags]) == 0
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "256", "--resume", "--no-progress"]) == 0
    assert json.loads((run / "config.json").read_text())["privileged_critic"] is True
    c = PPO.load(run / "latest.zip", device="cpu")
    with torch.no_grad():
        other = torch.cat([obs, -priv], 1)
        assert torch.equal(c.policy.get_distribution(full).distribution.mean,
                           c.policy.get_distribution(other).distribution.mean)
        assert not torch.allclose(c.policy.predict_values(full), c.policy.predict_values(other))
    # the exported actor: normalisation of the scans only, SB3's mean action (clipped to the range)
    ck = sorted((run / "checkpoints").glob("step_*.zip"))[-1]
    pol = checkpoint_policy(ck)
    with ck.with_suffix(".vecnorm.pkl").open("rb") as f:
        vn = pickle.load(f)
    raw = rng.uniform(0.2, 10.0, size=(8, n_scan + N_PRIVILEGED)).astype(np.float32)
    norm = np.clip((raw - vn.obs_rms.mean) / np.sqrt(vn.obs_rms.var + vn.epsilon), -vn.clip_obs, vn.clip_obs)
    c = PPO.load(ck, device="cpu")
    with torch.no_grad():
        want = c.policy.get_distribution(torch.as_tensor(norm, dtype=torch.float32)).distribution.mean.numpy()
    got = np.stack([pol(r[None, :n_scan])[0] for r in raw])
    assert np.allclose(got, np.clip(want, -1, 1), atol=1e-5)


@pytest.mark.parametrize("extra", [["--mirror-augment"], ["--bc-coef", "0.1", "--expert", "mirror"]])
def test_a_privileged_critic_refuses_what_reads_the_observation_as_scans(tmp_path, extra, capsys):
    from racecav.cli import main

    assert main(["train", "overtake", "--run-dir", str(tmp_path / "x"), "--steps", "0", "--privileged-critic",
                 *extra, *FLAGS]) != 0
    assert "--privileged-critic" in capsys.readouterr().out
