"""The world contract: what both backends (PyBullet: one world; the fast world: N) implement.

The gym env, the batched VecEnv, checkpoint selection and the parity tests use only these calls,
so either backend can stand behind them. Arrays have the worlds as their first axis (N = 1 for
PyBullet). tests/test_world_contract.py runs the same checks on both.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from racecav.common.lidar import LidarSpec


@runtime_checkable
class World(Protocol):
    """N worlds, each with the agent (car 0) and its obstacle cars."""

    n_envs: int
    spec: LidarSpec
    """The agent's lidar (observations are ``sanitize``-d ranges of it)."""

    @property
    def control_period(self) -> float:
        """Seconds per :meth:`step`."""

    @property
    def time(self) -> np.ndarray:
        """(N,) sim time (s) since each world's reset."""

    @property
    def time_limit(self) -> np.ndarray:
        """(N,) a scenario episode's duration (s); inf where the caller sets the limit (traffic)."""

    def seed(self, seed: int | None) -> None:
        """Seed the randomisation of the next reset."""

    def reset(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        """Reset every world. :return: observations (N, n_rays) float32."""

    def step(self, actions, brake=None) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], np.ndarray, dict]:
        """One control period with the agents' normalised actions (N, 2); ``brake`` (N,) bool:
        those agents brake (wheel speed target 0; common.vehicle.brake_from_action).

        :return: observations (N, n_rays); reward inputs (throttle T (N,), steering action
            clipped to [-1, 1] (N,)); collided (N,) bool (this step); info (backend-specific).
        """

    def agent_state(self) -> np.ndarray:
        """(N, 4) agent x, y, yaw (rad), forward speed (m/s)."""

    def set_state(self, env: int = 0, car: int = 0, *, x: float, y: float, yaw: float, v: float = 0.0,
                  delta: float = 0.0) -> None:
        """Teleport one car (parity tests, scripted scenes)."""

    def progress(self) -> np.ndarray:
        """(N,) agent progress (m) since the reset: along the centerline in its driving direction
        (loop worlds), else along its initial heading."""

    def success(self) -> np.ndarray:
        """(N,) no contact since the reset and at least the scenario's minimum progress."""

    def contact(self) -> np.ndarray:
        """(N,) the agent touched something since the reset."""

    def obstacles(self) -> np.ndarray:
        """(N, K, 4) x, y, yaw, speed of the obstacle cars."""
