"""A loss on the steering mean beyond the car's range (training/bounds.py, ``--steer-bound-coef``)."""

from __future__ import annotations

import json

import numpy as np
import torch

FLAGS = ["--preset", "fast", "--n-envs", "8", "--n-steps", "16", "--batch-size", "64", "--n-epochs", "2",
         "--checkpoint-every", "128", "--n-obstacles", "2", "--driver", "centerline", "--world", "figure8",
         "--lidar", "wide", "--ent-coef", "0.005", "--no-progress"]


def _model(coef: float, steer_bias: float, lr: float = 3e-4):
    from stable_baselines3.common.vec_env import VecNormalize

    from racecav.common.config import EnvConfig, TrainConfig
    from racecav.training.bounds import bounded_ppo, steer_bounds
    from racecav.training.env import env_car
    from racecav.training.train import make_venv

    tc = TrainConfig(env=EnvConfig(n_envs=4, n_obstacles=2, world="figure8", driver="centerline", lidar="wide"))
    venv = VecNormalize(make_venv(tc, seed=3))
    model = bounded_ppo()("MlpPolicy", venv, n_steps=16, batch_size=32, n_epochs=4, ent_coef=0.005, seed=0,
                          learning_rate=lr, device="cpu")
    model.bound_coef, model.bounds = coef, steer_bounds(env_car(tc.env))
    with torch.no_grad():
        model.policy.action_net.bias[1] = steer_bias
    return model


def test_penalty_is_the_squared_distance_beyond_the_range():
    from racecav.training.bounds import bound_penalty

    mean = torch.tensor([[0.0, -0.5], [0.0, -0.2], [0.0, 0.3], [0.0, 0.7]])
    assert torch.allclose(bound_penalty(mean, -0.263, 0.313), torch.tensor([0.237 ** 2, 0, 0, 0.387 ** 2]))


def test_the_term_adds_its_gradient_and_leaves_the_entropy_value():
    """PPO's entropy loss ``-ent_coef * mean(entropy)`` over the wrapped entropy has the entropy's
    value and the gradient of that loss plus ``coef * mean(P)``."""
    from racecav.training.bounds import bound_penalty, with_bound_term
    from racecav.training.dagger import mean_action

    model = _model(coef=3.0, steer_bias=0.5)
    policy = model.policy
    obs = torch.as_tensor(np.random.default_rng(0).normal(size=(64, policy.observation_space.shape[0])),
                          dtype=torch.float32)
    actions = torch.zeros(64, 2)
    assert (bound_penalty(mean_action(policy, obs), *model.bounds) > 0).float().mean() > 0.5  # mostly beyond
    _, _, wrapped = with_bound_term(policy, 3.0, model.bounds, 0.005)(obs, actions)
    _, _, plain = policy.evaluate_actions(obs, actions)
    assert torch.allclose(wrapped, plain)

    def grad(loss):
        policy.zero_grad()
        loss.backward()
        return policy.action_net.bias.grad.clone()

    want = grad(-0.005 * plain.mean() + 3.0 * bound_penalty(mean_action(policy, obs), *model.bounds).mean())
    _, _, wrapped = with_bound_term(policy, 3.0, model.bounds, 0.005)(obs, actions)
    assert torch.allclose(grad(-0.005 * wrapped.mean()), want, atol=1e-6) and want[1] > 0.1


def test_updates_pull_a_saturated_steering_mean_back_to_the_range():
    """From a steering mean far beyond the left limit, the same rollouts move it back to within
    the range with the term and leave it beyond without (same seed: plain PPO)."""
    from racecav.training.dagger import mean_action

    means = {}
    for coef in (0.0, 10.0):
        model = _model(coef, steer_bias=1.5, lr=0.01)
        model.learn(256)
        obs = model.rollout_buffer.observations.reshape(-1, model.rollout_buffer.obs_shape[0])
        with torch.no_grad():
            means[coef] = float(mean_action(model.policy, torch.as_tensor(obs))[:, 1].median())
    assert means[0.0] > 1.0 and means[10.0] < 0.313 + 0.2, means


def test_run_records_the_flag_resumes_and_refuses_without_entropy(tmp_path):
    from racecav.cli import main

    run = tmp_path / "bound"
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "128", "--steer-bound-coef", "10", *FLAGS]) == 0
    assert main(["train", "overtake", "--run-dir", str(run), "--steps", "256", "--resume", "--no-progress"]) == 0
    assert json.loads((run / "config.json").read_text())["steer_bound_coef"] == 10
    assert (run / "progress.csv").read_text().splitlines()[-1].split(",")[0] == "256"
    flags = [f if f != "0.005" else "0" for f in FLAGS]
    assert main(["train", "overtake", "--run-dir", str(tmp_path / "no"), "--steps", "128", "--steer-bound-coef", "1",
                 *flags]) == 2
