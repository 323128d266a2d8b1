"""PPO that also learns from its rollouts seen in a mirror: ``racecav train overtake --mirror-augment``.

Row 16 (shipped as avoid 2026-12-01 to 02) passes both timings of the crossings from its right,
and its own mirror image passes both from the left (``racecav train mirror``, docs/training.md):
the skill is in the network, on one side. Fitting the mirrored actions by regression moved the
other evasions (row 22), and an actor symmetric by construction had to start from scratch (row
23). Here PPO keeps its objective and its clip, and every update also sees each sample of the
rollout reflected: the scans of each stacked scan reversed, the steering negated, the same
reward, return and advantage (the reward is symmetric: 5 T^2, the steering-flip penalty,
progress along the road). The old log-probability of a reflected sample is the policy's own
before the update, so PPO's ratio starts at 1 and its clip bounds how far one update moves the
other side towards the reflected experience (the usual symmetry augmentation for PPO, e.g.
Mittal et al. 2024, "Symmetry considerations for learning task symmetric robot policies").

The world is only nearly symmetric: the car steers 0.313 rad to the left and 0.263 to the right
(common/data/cars/slash.toml), so a reflected left turn beyond 0.263 rad is one the car clips,
and the wide view's rays are reflected to within half a ray spacing (training/mirror.py).
Each update costs about twice as much (twice the samples per epoch). Measured from the
lopsided row 16 (docs/training.md, row 24): it collapses within 0.5 M samples, the way
from one turn for every car to a turn for each side passing through no turn at all.
"""

from __future__ import annotations

import numpy as np

from racecav.training.mirror import mirror_scans

BUFFER_FIELDS = ("observations", "actions", "rewards", "returns", "episode_starts", "values", "log_probs",
                 "advantages")
"""The RolloutBuffer arrays, each (n_steps, n_envs, ...): the reflected copy is appended on the env axis."""


def mirror_normalized(obs: np.ndarray, obs_stack: int, vecnorm=None) -> np.ndarray:
    """Normalised observations ``obs`` seen in a mirror: the raw scans (VecNormalize's statistics
    are not symmetric) reflected and normalised again."""
    if vecnorm is None:
        return mirror_scans(obs, obs_stack)
    rms = vecnorm.obs_rms
    std = np.sqrt(rms.var + vecnorm.epsilon)
    raw = mirror_scans(obs * std + rms.mean, obs_stack)
    return np.clip((raw - rms.mean) / std, -vecnorm.clip_obs, vecnorm.clip_obs).astype(obs.dtype)


def augment_buffer(model, obs_stack: int) -> int:
    """Append the reflected copy of ``model``'s filled rollout buffer (on the env axis) and return
    the buffer's own env count (to restore after the update)."""
    import torch

    from racecav.training.mirror import mirror_action

    buf = model.rollout_buffer
    n_envs = buf.n_envs
    obs = mirror_normalized(buf.observations, obs_stack, model.get_vec_normalize_env())
    acts = mirror_action(buf.actions)
    with torch.no_grad():
        _, log_prob, _ = model.policy.evaluate_actions(torch.as_tensor(obs.reshape(-1, obs.shape[-1])),
                                                       torch.as_tensor(acts.reshape(-1, acts.shape[-1])))
    mirrored = {"observations": obs, "actions": acts,
                "log_probs": log_prob.numpy().reshape(buf.log_probs.shape).astype(buf.log_probs.dtype)}
    for name in BUFFER_FIELDS:
        a = getattr(buf, name)
        setattr(buf, name, np.concatenate([a, mirrored.get(name, a)], axis=1))
    buf.n_envs = 2 * n_envs
    return n_envs


def mirror_augmented_ppo():
    """The PPO subclass (SB3 imported lazily, like the rest of training)."""
    from stable_baselines3 import PPO

    class MirrorAugmentedPPO(PPO):
        """PPO whose updates also fit the reflected rollout. ``mirror_obs_stack`` (scans per
        observation) is set by training/train.py after construction or load."""

        mirror_obs_stack: int = 1

        def train(self) -> None:
            n_envs = augment_buffer(self, self.mirror_obs_stack)
            try:
                super().train()
            finally:
                # collect_rollouts' reset() allocates the buffer for the real envs again
                self.rollout_buffer.n_envs = n_envs

    return MirrorAugmentedPPO
