"""A reward term for evading with a crossing car's flow: ``racecav train overtake ... --flow-reward W``.

Row 16 (shipped as avoid 2026-12-01 to 02) turns left at the intersection whatever the side the
car crosses from (docs/training.md, the ablation's row 16). For a car from the right, moving to
the ego's left, that turn runs ahead of the car in its own direction of travel and passes both
timings (paper right-to-left 100 %, conflict-timed 99 %, selection seeds); for a car from the
left it enters the road the car is coming down, which passes only when the car has gone
(conflict-timed 98 %, paper-timed 51 %). Its mirror image turns right and passes both timings
from the left (98 / 99 %, measured by ``racecav train mirror`` at commit 3a95a65): the evasion that does not depend on the
timing is the one with the car's flow. PPO does not find it from the left-turn habit (row 16's
steering std is 0.09, and where its mean steering lies beyond the car's range the actuation
clips the noise away), so this term pays for it while it is being learnt: W per metre the ego
moves along the direction of travel of a crossing car (heading 45-135 deg from the ego's road)
that moves and is within NEAR_M, negative against it. It reads the actors' state (privileged,
training only); the policy sees only its scans. Measured:
docs/training.md, rows 25-27."""

from __future__ import annotations

import numpy as np

NEAR_M = 4.0        # m: a crossing car this near (centre to centre) shapes the ego's motion
MOVING_MS = 0.2     # m/s: a stopped car has no flow
CROSSING_SIN = np.sin(np.deg2rad(45.0))  # |sin| of the heading difference: 45-135 deg is a crossing


def flow_weights(world) -> np.ndarray:
    """(N, 2): for each env of a scenario ``world``, the sum of the unit directions of travel of
    the crossing, moving cars near its ego (zero where none is), before the step."""
    out = np.zeros((world.n_envs, 2))
    if world.actors is None:
        return out
    dx, dy = world.x[:, 1:] - world.x[:, :1], world.y[:, 1:] - world.y[:, :1]
    rel = world.yaw[:, 1:] - world.start_pose[:, 2:3]  # crossing the ego's road, not its current heading
    sel = (world.active[:, 1:] & (np.hypot(dx, dy) < NEAR_M) & (world.v[:, 1:] > MOVING_MS)
           & (np.abs(np.sin(rel)) > CROSSING_SIN))
    out[:, 0] = np.where(sel, np.cos(world.yaw[:, 1:]), 0.0).sum(axis=1)
    out[:, 1] = np.where(sel, np.sin(world.yaw[:, 1:]), 0.0).sum(axis=1)
    return out


def flow_reward(weight: float, directions: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """``weight`` x the ego's displacement (dx, dy) over the step along ``directions`` (flow_weights)."""
    return (weight * (directions[:, 0] * dx + directions[:, 1] * dy)).astype(np.float32)
