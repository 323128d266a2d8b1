"""A critic that sees what the actor cannot (``racecav train overtake ... --privileged-critic``).

Why: the avoid policy has to tell a paper-timed crossing car from a conflict-timed one about
2 m before the crossing, from a car that has just come out from behind the intersection's
corner (docs/training.md, "When the view tells the two timings apart"). Its critic sees the same
scans, so it values both timings alike until they differ in the scan, and PPO's advantage of the
early decision is the average over both. Given the other cars' positions and velocities, the
critic knows which timing an episode has from its first step, and each decision is credited
with what it led to (asymmetric actor-critic: Pinto et al. 2018, "Asymmetric Actor Critic for
Image-Based Robot Learning"). The actor still reads only the scans: it is the policy that ships,
and the car provides nothing more.

The VecEnv appends N_PRIVILEGED features to each observation (FastVecEnv(privileged=True));
PrivilegedCriticPolicy's actor reads the first ``actor_inputs`` of them, its critic all.
Exported policies (common/policy.py) keep the actor and its inputs' normalisation only.

Measured (docs/training.md, rows 47-48, from row 31's 5 M): PPO's explained variance rises from
0.76 to 0.87, and the actor's results stay in row 31's range (paper-timed left-to-right 75-92 %);
with row 46's margin term, 69-84 %. No shipped policy uses it.
"""

from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

NEAREST = 3
"""Other cars the critic sees, nearest first."""
N_PRIVILEGED = 2 + 4 * NEAREST
"""Ego speed, time left in the episode, then per car: x, y, vx, vy relative to the ego, in its frame."""
POS_SCALE, SPEED_SCALE, TIME_SCALE = 4.0, 2.0, 10.0  # m, m/s, s: features of order 1
ABSENT = (3.0, 0.0, 0.0, 0.0)  # a missing car: 12 m ahead, at rest relative to the ego


def privileged_features(world) -> np.ndarray:
    """(N, N_PRIVILEGED) float32 features of each of ``world``'s envs in its current state."""
    n = world.n_envs
    out = np.empty((n, N_PRIVILEGED), dtype=np.float32)
    v0, yaw0 = world.v[:, 0], world.yaw[:, 0]
    out[:, 0] = v0 / SPEED_SCALE
    out[:, 1] = np.clip(world.time_limit - world.time, 0.0, 60.0) / TIME_SCALE
    cars = np.tile(np.asarray(ABSENT, np.float32), (n, NEAREST))
    if world.x.shape[1] > 1:
        c, s = np.cos(yaw0)[:, None], np.sin(yaw0)[:, None]
        dx, dy = world.x[:, 1:] - world.x[:, :1], world.y[:, 1:] - world.y[:, :1]
        vx = world.v[:, 1:] * np.cos(world.yaw[:, 1:]) - (v0 * np.cos(yaw0))[:, None]
        vy = world.v[:, 1:] * np.sin(world.yaw[:, 1:]) - (v0 * np.sin(yaw0))[:, None]
        rel = np.stack([(c * dx + s * dy) / POS_SCALE, (-s * dx + c * dy) / POS_SCALE,
                        (c * vx + s * vy) / SPEED_SCALE, (-s * vx + c * vy) / SPEED_SCALE], axis=-1)
        dist = np.where(world.active[:, 1:], np.hypot(dx, dy), np.inf)
        order = np.argsort(dist, axis=1)[:, :NEAREST]
        rows = np.arange(n)[:, None]
        near = rel[rows, order]  # (n, k, 4)
        near[~np.isfinite(dist[rows, order])] = ABSENT
        cars[:, :4 * order.shape[1]] = near.reshape(n, -1)
    out[:, 2:] = cars
    return out


class ActorInputs(BaseFeaturesExtractor):
    """The actor's features: the first ``n`` observation entries (the scans)."""

    def __init__(self, observation_space, n: int):
        super().__init__(observation_space, n)
        self.n = n

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return obs[:, :self.n]


class SplitMlp(nn.Module):
    """SB3's MlpExtractor (separate actor and critic MLPs, tanh) with inputs of two widths."""

    def __init__(self, actor_dim: int, critic_dim: int, net_arch: list[int], activation_fn):
        super().__init__()

        def mlp(n_in):
            layers = []
            for width in net_arch:
                layers += [nn.Linear(n_in, width), activation_fn()]
                n_in = width
            return nn.Sequential(*layers)

        self.policy_net, self.value_net = mlp(actor_dim), mlp(critic_dim)
        self.latent_dim_pi = self.latent_dim_vf = net_arch[-1]

    def forward(self, features):
        pi, vf = features
        return self.forward_actor(pi), self.forward_critic(vf)

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        return self.policy_net(features)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        return self.value_net(features)


class PrivilegedCriticPolicy(ActorCriticPolicy):
    """SB3's MlpPolicy whose actor reads the first ``actor_inputs`` observation entries and whose
    critic reads all of them. The state dict keeps MlpPolicy's keys, so the actor exports and
    loads as any MlpPolicy's (common/policy.policy_arrays_from_sb3)."""

    def __init__(self, *args, actor_inputs: int, **kwargs):
        self.actor_inputs = int(actor_inputs)
        kwargs["share_features_extractor"] = False
        super().__init__(*args, **kwargs)

    def _build_mlp_extractor(self) -> None:
        self.pi_features_extractor = ActorInputs(self.observation_space, self.actor_inputs)
        arch = self.net_arch if isinstance(self.net_arch, list) else self.net_arch["pi"]
        self.mlp_extractor = SplitMlp(self.actor_inputs, self.features_dim, list(arch), self.activation_fn)

    def _get_constructor_parameters(self) -> dict:
        return {**super()._get_constructor_parameters(), "actor_inputs": self.actor_inputs}
