"""A mirror-symmetric actor: ``racecav train overtake ... --mirror-symmetric``.

The intersection families come in mirror pairs, yet a trained policy is rarely symmetric: the
avoid shipped on 2026-12-01 (row 16) passes the crossings from its right in both timings and
fails half of the paper-timed ones from its left, while its own mirror image passes those
(``racecav train mirror``, training/checkpoints/mirror-avoid.md). An actor that is symmetric by
construction, actor(mirrored scans) = mirrored actor(scans) (steering negated), learns each side
from both sides' episodes and cannot trade one side against the other.

The actor stays SB3's MlpPolicy network, 2 x 64 tanh, so the export, the numpy path, the fused
kernel and their equality tests are unchanged; only its weights are tied (the usual
equivariant-layer construction, e.g. Ravanbakhsh et al. 2017; mirror symmetry in RL:
Abdolhosseini et al. 2019). The hidden units of both layers come in pairs (2k, 2k+1) that see
the scans and their mirror image: unit 2k+1's input weights are unit 2k's, mirrored; throttle
reads both units of a pair alike and steering with opposite signs (no steering bias). The tie is
kept by projection: after every optimizer step the weights are replaced by the nearest tied
weights (the mean of each pair, TiedWeights.project). The critic is left free. The observation
statistics of VecNormalize are kept symmetric too (SymmetricStats), or the normalisation
would break the symmetry the weights have.
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.policies import ActorCriticPolicy


def mirror_index(obs_dim: int, obs_stack: int) -> np.ndarray:
    """Input permutation of the mirror: each stacked scan's rays reversed (training/mirror.py)."""
    if obs_dim % obs_stack:
        raise ValueError(f"mirror: obs_stack {obs_stack} does not divide the input size {obs_dim}")
    n = obs_dim // obs_stack
    return np.concatenate([k * n + np.arange(n)[::-1] for k in range(obs_stack)])


def pair_swap(n: int) -> np.ndarray:
    """Hidden-unit permutation of the mirror: unit 2k <-> 2k+1."""
    if n % 2:
        raise ValueError(f"mirror: a hidden layer of {n} units has no pairs")
    return np.arange(n).reshape(-1, 2)[:, ::-1].reshape(-1)


class TiedWeights:
    """Projection of an MlpPolicy actor's weights onto the mirror-symmetric ones."""

    def __init__(self, policy, obs_stack: int):
        import torch

        net = policy.mlp_extractor.policy_net
        self.layers = [m for m in net if isinstance(m, torch.nn.Linear)]
        if len(self.layers) != 2:
            raise ValueError(f"mirror: expected 2 hidden layers in the actor, found {len(self.layers)}")
        self.action = policy.action_net
        self.m_in = torch.as_tensor(mirror_index(self.layers[0].in_features, obs_stack))
        self.swaps = [torch.as_tensor(pair_swap(lin.out_features)) for lin in self.layers]

    def project(self) -> None:
        """The nearest tied weights (the mean of each pair and its mirror), in place."""
        import torch

        with torch.no_grad():
            perms = [self.m_in, self.swaps[0]]  # what the mirror does to each layer's input
            for lin, p_in in zip(self.layers, perms):
                w, b = lin.weight, lin.bias
                even = 0.5 * (w[0::2] + w[1::2][:, p_in])
                w[0::2], w[1::2] = even, even[:, p_in]
                be = 0.5 * (b[0::2] + b[1::2])
                b[0::2], b[1::2] = be, be
            p = self.swaps[1]
            w, b = self.action.weight, self.action.bias
            w[0] = 0.5 * (w[0] + w[0][p])   # throttle: symmetric
            w[1] = 0.5 * (w[1] - w[1][p])   # steering: antisymmetric
            b[1] = 0.0


class MirrorMlpPolicy(ActorCriticPolicy):
    """MlpPolicy whose actor is mirror-symmetric (``obs_stack`` scans per observation)."""

    def __init__(self, *args, obs_stack: int = 1, **kwargs):
        self.obs_stack = obs_stack
        super().__init__(*args, **kwargs)
        self.tied = TiedWeights(self, obs_stack)
        self.tied.project()
        step = self.optimizer.step

        def projected_step(*a, **k):
            out = step(*a, **k)
            self.tied.project()
            return out

        self.optimizer.step = projected_step

    def _get_constructor_parameters(self) -> dict:
        return {**super()._get_constructor_parameters(), "obs_stack": self.obs_stack}


def symmetric_stats_callback(obs_stack: int):
    """An SB3 callback that keeps VecNormalize's observation statistics mirror-symmetric (the mean
    and variance of each ray and its mirror averaged after every step)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class SymmetricStats(BaseCallback):
        def _on_step(self) -> bool:
            vn = self.model.get_vec_normalize_env()
            if vn is not None:
                symmetrize_stats(vn.obs_rms, obs_stack)
            return True

    return SymmetricStats()


def symmetrize_stats(rms, obs_stack: int) -> None:
    """``rms`` (a RunningMeanStd over stacked scans) made mirror-symmetric, in place."""
    m = mirror_index(rms.mean.shape[0], obs_stack)
    rms.mean = 0.5 * (rms.mean + rms.mean[m])
    rms.var = 0.5 * (rms.var + rms.var[m])
