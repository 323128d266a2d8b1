"""Hold the road until a car is in view: the training reward terms ``racecav train overtake ...
--hold-heading W`` (EnvConfig.hold_heading) and ``--hold-track W`` (EnvConfig.hold_track) of the
fast VecEnv.

Why: row 31 (the shipped avoid) turns left at every intersection, and starts the turn about
2.7 m before the crossing, while the intersection's corners still hide a car coming down the
crossing road (it is in the scan from about 2-3 m out; FastWorld.seen_by_agent). A car timed like
the paper's is then still 3 m up that road, and the ego passes it there head-on, 0.4-0.7 m
between the centres, touching in about one trial in six (paper-timed left-to-right 80-83 %),
where a straight ego passes ahead of it (100 %). An evasion that starts before anything is seen
is a habit, not a reaction.

``--hold-heading W`` charges W per radian of heading away from the ego's road at each step of a
scenario episode until a car has returned a ray of the ego's scan, so turns are paid for only once
they answer a car. Measured (docs/training.md, row 43, W = 30 from row 31's 5 M): row 31's range
(paper-timed left-to-right 73-88 % over 3.6 M samples). The heading error before the car is in
view is small, and the latch pays a drift that shows the car earlier: row 31 has the paper-timed
car in its scan before the crossing in 91 % of the episodes, a straight ego in 32 %.

``--hold-track W`` charges the whole departure from a straight pass at full throttle: W x
(|lateral offset| (m) + |heading error| (rad) + (1 - T)) per step, T the throttle, until a car
is in the scan of a ghost that kept the road: the ego's pose moved onto its road's centre line at
the same progress, with the road's heading (FastWorld.seen_by_agent with ``pose``). A drift then
buys nothing: the term ends when a straight ego would see the car, wherever the ego is. This is
the probe's seeing planner (training/probe.seen_decision: 100 % of the paper-timed crossings from
the left, 77 % of the conflict-timed ones when freed at first sight) as a reward, not as labels to
imitate (imitating the planner collapses, row 49). Measured (docs/training.md, row 50, W = 10
from row 31's 5 M, 38.8 M samples): the departure shrinks little, PPO's explained variance falls
to 0.14-0.42, and the paper-timed left-to-right is 55-93 % over 36 checkpoints; rejected.

Both read the world (line of sight, privileged, training only, like flow_reward.py); the policy
sees only its scans. Traffic episodes get no term. Cost: one agent scan per other car and
scenario world per step (one more for the ghost). No shipped policy uses them.
"""

from __future__ import annotations

import numpy as np


class HoldRoad:
    """The term for one FastVecEnv batch, with its per-episode latch: once a car has been in view
    the term is off until the episode ends (an evasion may leave the road for good, e.g. up the
    crossing road, and the car it answered is then behind the ego, out of view).

    :param n: rows of the batch.
    :param heading: reward per radian of heading error per step.
    :param lateral: reward per metre of lateral offset from the road's line per step.
    :param throttle: reward per unit of throttle below full (1 - T) per step.
    :param ghost: the latch trips when a car is in the view of the ego moved onto its road (the
        ghost), not in the ego's own view.
    """

    def __init__(self, n: int, heading: float, lateral: float = 0.0, throttle: float = 0.0, ghost: bool = False):
        self.heading, self.lateral, self.throttle, self.ghost = heading, lateral, throttle, ghost
        self.seen = np.zeros(n, dtype=bool)

    @classmethod
    def from_settings(cls, n: int, settings) -> "HoldRoad | None":
        """The term an EnvConfig asks for (None: neither hold_heading nor hold_track)."""
        if settings.hold_track:
            w = settings.hold_track
            return cls(n, heading=w, lateral=w, throttle=w, ghost=True)
        if settings.hold_heading:
            return cls(n, heading=settings.hold_heading)
        return None

    def step(self, world, sl: slice, throttle: np.ndarray) -> np.ndarray:
        """(n_envs of ``world``,) the term for its current state (after a step) in the batch rows
        ``sl``, ``throttle`` the step's a_T (charged as T = clip(a_T, 0, 1)); 0 for a traffic world."""
        out = np.zeros(world.n_envs, dtype=np.float32)
        if world.actors is None:
            return out
        x0, y0, yaw0 = world.start_pose.T
        dx, dy = world.x[:, 0] - x0, world.y[:, 0] - y0
        seen = self.seen[sl]  # a view: the latch is updated in place
        todo = np.flatnonzero(~seen)
        if todo.size:
            ghost = None
            if self.ghost:  # the ego moved onto its road at its progress along it
                s, x, y, yaw = world.progress()[todo], x0[todo], y0[todo], yaw0[todo]
                ghost = np.stack([x + s * np.cos(yaw), y + s * np.sin(yaw), yaw], axis=1)
            seen[todo] = world.seen_by_agent(todo, pose=ghost).any(axis=1)
        cost = self.heading * np.abs(np.angle(np.exp(1j * (world.yaw[:, 0] - yaw0))))
        if self.lateral:
            cost = cost + self.lateral * np.abs(dy * np.cos(yaw0) - dx * np.sin(yaw0))
        if self.throttle:
            cost = cost + self.throttle * (1.0 - np.clip(throttle, 0.0, 1.0))
        out[:] = np.where(seen, 0.0, -cost)
        return out

    def reset(self, dones: np.ndarray) -> None:
        """New episodes in the rows ``dones`` (bool over the batch): nothing seen yet."""
        self.seen[dones] = False
