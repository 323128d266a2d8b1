"""Hold the road's heading until a car is in view: a training reward term of the fast VecEnv
(``racecav train overtake ... --hold-heading W``, EnvConfig.hold_heading).

Why: row 31 (the shipped avoid) turns left at every intersection, and starts the turn about
2.7 m before the crossing, while the intersection's corners still hide a car coming down the
crossing road (it is in the scan from about 2 m out; FastWorld.seen_by_agent). A car timed like
the paper's is then still 3 m up that road, and the ego passes it there head-on, 0.4-0.7 m
between the centres, touching in about one trial in six (paper-timed left-to-right 80-83 %),
where a straight ego passes ahead of it (100 %). An evasion that starts before anything is seen
is a habit, not a reaction: this term charges W per radian of heading away from the ego's road
at each step of a scenario episode until a car has returned a ray of the ego's scan, so turns
are paid for only once they answer a car.

It reads the world (line of sight, privileged, training only, like flow_reward.py); the policy
sees only its scans. Traffic episodes get no term. Cost: one agent scan per other car and
scenario world per step (FastWorld.seen_by_agent).

Measured (docs/training.md, row 43, ``--hold-heading 30`` from row 31's 5 M): row 31's range
(paper-timed left-to-right 73-88 % over 3.6 M samples). The heading error before the car is in
view is small: the sharp part of the turn comes once the car is seen. No shipped policy uses it.
"""

from __future__ import annotations

import numpy as np


class HoldHeading:
    """The term for one FastVecEnv batch, with its per-episode latch: once a car has been in view
    the term is off until the episode ends (an evasion may leave the road for good, e.g. up the
    crossing road, and the car it answered is then behind the ego, out of view).

    :param n: rows of the batch.
    :param weight: reward per radian of heading error per step.
    """

    def __init__(self, n: int, weight: float):
        self.weight = weight
        self.seen = np.zeros(n, dtype=bool)

    def step(self, world, sl: slice) -> np.ndarray:
        """(n_envs of ``world``,) the term for its current state (after a step) in the batch rows
        ``sl``; 0 for a traffic world."""
        out = np.zeros(world.n_envs, dtype=np.float32)
        if world.actors is None:
            return out
        seen = self.seen[sl]  # a view: the latch is updated in place
        todo = np.flatnonzero(~seen)
        seen[todo] = world.seen_by_agent(todo).any(axis=1)
        err = np.abs(np.angle(np.exp(1j * (world.yaw[:, 0] - world.start_pose[:, 2]))))
        out[:] = np.where(seen, 0.0, -self.weight * err)
        return out

    def reset(self, dones: np.ndarray) -> None:
        """New episodes in the rows ``dones`` (bool over the batch): nothing seen yet."""
        self.seen[dones] = False
