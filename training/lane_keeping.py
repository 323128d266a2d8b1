"""Keep the lane while it is free: a training reward term of the fast VecEnv (EnvConfig.lane_keeping).

Why: a crossing car timed like the paper's (a straight ego passes ahead of it) and one timed to
meet the ego look alike in the policy's view until the ego is about 2 m from the crossing
(``racecav train probe``, docs/training.md), yet the privileged planner, held straight until
2 m out, still passes both timings (it fails most conflict-timed ones from 1.5 m). PPO's
policies commit to an evasion earlier, between 2.5 and 2 m, and so turn into cars that would
have passed. This term charges steering away from plain tracking while tracking would pass
free, so the cheapest way to survive both timings is to keep the lane and evade late.

"Free" is privileged: the planner's look-ahead (training/expert.Expert, plain tracking at full
throttle only) steps an exact copy of the world, synchronised actors included. The term exists
in scenario episodes only (traffic episodes get no term); the policy never sees it, so nothing changes on the car.

Measured (row 19 of the ablation, docs/training.md): from row 16's avoid it does not teach
the late evasion within 11 M samples (its checkpoints score below row 16's), and the
look-ahead cuts the training throughput by about four. No shipped policy uses it.
"""

from __future__ import annotations

import numpy as np

from racecav.training.expert import Expert


class LaneKeeping:
    """The term for the scenario worlds of one FastVecEnv batch.

    :param worlds: the batch's FastWorlds; traffic worlds (no actors) get no term.
    :param slices: each world's rows in the batch.
    :param weight: reward per unit of |a_delta - tracking steer| (action units, [-1, 1]).
    :param horizon_s: the look-ahead of "tracking passes free".
    """

    CONTACT = -500.0  # Expert scores a contact below -1000 + horizon steps

    def __init__(self, worlds: list, slices: list, weight: float, horizon_s: float):
        self.weight = weight
        self.checks = [(sl, Expert(w, horizon_s, track_only=True)) for w, sl in zip(worlds, slices)
                       if w.actors is not None]

    def penalty(self, actions: np.ndarray) -> np.ndarray:
        """(N,) the term (<= 0) for ``actions`` (N, 2) taken from the worlds' current state."""
        out = np.zeros(len(actions), dtype=np.float32)
        for sl, e in self.checks:
            free = e.scores()[:, 0] > self.CONTACT
            dev = np.abs(np.clip(actions[sl, 1], -1.0, 1.0) - e.first_track)
            out[sl] = np.where(free, -self.weight * dev, 0.0)
        return out
