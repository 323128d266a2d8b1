"""PPO with a loss on the steering mean beyond the car's range: ``--steer-bound-coef C``.

The car clips the steering action to [delta_min, delta_max] (common/vehicle.py). Near a crossing
car the steering mean of row 16 (shipped as avoid 2026-12-01 to 02) is often beyond that range
(a one-off count in issue 15's notes): there its exploration noise (std 0.08, its log_std) and
small changes of its mean do not change what the car does, so PPO gets no signal that a smaller
or an opposite turn would pass. The loss ``C * mean(relu(mu - hi)^2 + relu(lo - mu)^2)`` on the
steering mean ``mu`` pulls it back to the edge of the range, where the deterministic action, and
so the car, is the same, but the sampled actions do vary the turn (the "bounds loss" of
rl_games' PPO, there on every action dimension).

SB3's PPO has no hook for an extra loss term. The term enters through the entropy that the policy
returns to PPO's loss (``ent_coef * -mean(entropy)``): ``entropy - (P - P.detach()) / ent_coef``
has the entropy's value, so the logged entropy is unchanged, and adds exactly the gradient of
``mean(P)`` to the loss. Hence ``ent_coef > 0`` is required.

Measured (docs/training.md, row 28): from row 16 the term takes the mean back into the
range, but the paper-timed left-to-right falls to 0-17 % and the conflict-timed head-on to 39-59 %;
rejected.
"""

from __future__ import annotations

import numpy as np

STEER = 1  # the steering component of the action


def bound_penalty(mean, lo: float, hi: float):
    """Per-sample squared distance (torch) of the steering mean beyond [lo, hi]."""
    import torch

    mu = mean[:, STEER]
    return torch.relu(mu - hi) ** 2 + torch.relu(lo - mu) ** 2


def steer_bounds(car) -> tuple[float, float]:
    """The steering actions that still change the car's command (training/dagger.action_bounds)."""
    from racecav.training.dagger import action_bounds

    lo, hi = action_bounds(car)
    return float(lo[STEER]), float(hi[STEER])


def with_bound_term(policy, coef: float, bounds: tuple[float, float], ent_coef: float):
    """``policy.evaluate_actions`` whose entropy carries the gradient of ``coef * mean(P)`` (see
    above)."""
    from racecav.training.dagger import mean_action

    evaluate = policy.evaluate_actions

    def evaluate_with_bound(obs, actions):
        values, log_prob, entropy = evaluate(obs, actions)
        penalty = bound_penalty(mean_action(policy, obs), *bounds)
        if entropy is None:  # SB3's entropy of a distribution without a closed form
            entropy = -log_prob
        return values, log_prob, entropy - coef * (penalty - penalty.detach()) / ent_coef

    return evaluate_with_bound


def bounded_ppo():
    """The PPO subclass (SB3 imported lazily, like the rest of training)."""
    from stable_baselines3 import PPO

    class SteerBoundedPPO(PPO):
        """PPO whose loss also pulls the steering mean into the car's range. ``bound_coef`` and
        ``bounds`` are set by training/train.py after construction or load."""

        bound_coef: float = 0.0
        bounds: tuple[float, float] = (-np.inf, np.inf)

        def train(self) -> None:
            if self.ent_coef <= 0:
                raise ValueError("--steer-bound-coef enters PPO's loss through the entropy term: "
                                 "it needs --ent-coef > 0")
            self.policy.evaluate_actions = with_bound_term(self.policy, self.bound_coef, self.bounds, self.ent_coef)
            try:
                super().train()
            finally:
                del self.policy.evaluate_actions  # the class's method again

    return SteerBoundedPPO
