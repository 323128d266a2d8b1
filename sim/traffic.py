"""Drivers of the obstacle cars lapping a loop world, for both backends, and their one factory.

A driver returns normalised actions (a_T, a_delta) for the obstacle cars, which go through the
same actuation (:mod:`racecav.common.vehicle`) as the agent. :func:`make_driver` turns a name
(``pure_pursuit`` = ``centerline``, ``policy:NAME_OR_PATH``), a policy callable or a driver object
into the driver a backend calls:

- PyBullet (one world): ``reset(world, car, n, rng)`` then ``act(TrafficObs) -> (n, 2|3)``;
- the fast world (N worlds batched): ``driver(fast_world) -> (N, C-1, 2)``.

The pure-pursuit centerline follower has one implementation per backend, as the vehicle model
does: :class:`PurePursuitDriver` (per car, numpy) and :class:`CenterlineDriver` (batched numba
kernel, slowing for curves); :class:`PolicyDriver` (a trained policy on each car's own scan, e.g.
the racing policy) serves both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from racecav.common.vehicle import CarParams
from racecav.common.world import World
from racecav.sim import fast_kernels as K


@dataclass
class TrafficObs:
    """What a traffic driver observes at a control step."""

    poses: np.ndarray
    """(n, 3) x, y, yaw of the obstacle cars."""
    speeds: np.ndarray
    """(n,) forward speeds (m/s)."""
    others: np.ndarray
    """(m, 3) poses of the other cars (the agent) they must not run into."""
    scans: np.ndarray | None
    """(n, n_rays) sanitized lidar observations, or None if the driver does not need them."""
    t: float


class TrafficDriver:
    """Interface of an obstacle-car driver."""

    needs_lidar: bool = False
    """True if act() needs ``TrafficObs.scans`` (the world then casts rays for every car)."""

    def reset(self, world: World, car: CarParams, n: int, rng: np.random.Generator) -> None:
        """Start of an episode: ``n`` obstacle cars on ``world``."""

    def act(self, obs: TrafficObs) -> np.ndarray:
        """Actions (n, 2): a_T, a_delta in [-1, 1] per obstacle car (the agent's action space),
        or (n, 3) with a third column > 0.5 = brake (wheel speed target 0): traffic cars may
        brake, the agent's action space has no brake (paper)."""
        raise NotImplementedError


class PurePursuitDriver(TrafficDriver):
    """Follows the centerline (each car at its own lateral offset) with pure pursuit at full
    throttle; coasts when a car driving the same way is close ahead in its lane, brakes when
    it is very close (a queue behind a stopped car must not pile up)."""

    def __init__(self, lookahead: float = 1.0, lookahead_per_speed: float = 0.3,
                 lateral_range: float = 0.35, throttle: float = 1.0, gap_m: float = 1.5,
                 brake_gap_m: float = 1.0, lane_halfwidth: float = 0.45):
        """
        :param lookahead: pure-pursuit lookahead at standstill (m).
        :param lookahead_per_speed: extra lookahead per m/s of speed (s).
        :param lateral_range: each car keeps a random lateral offset in +- this (m).
        :param throttle: throttle when the way is free.
        :param gap_m: coast when a car ahead (same direction, same lane) is closer than this
            (arc length between the car frames, m).
        :param brake_gap_m: brake when it is closer than this.
        :param lane_halfwidth: lateral distance under which a car ahead counts as in the lane.
        """
        self.lookahead, self.k_v = lookahead, lookahead_per_speed
        self.lateral_range, self.throttle = lateral_range, throttle
        self.gap_m, self.brake_gap_m, self.lane_halfwidth = gap_m, brake_gap_m, lane_halfwidth

    def reset(self, world: World, car: CarParams, n: int, rng: np.random.Generator) -> None:
        self.world, self.car = world, car
        self.offsets = rng.uniform(-self.lateral_range, self.lateral_range, n)

    def act(self, obs: TrafficObs) -> np.ndarray:
        w, car = self.world, self.car
        x, y, yaw = obs.poses.T
        everyone = np.vstack([obs.poses, obs.others]) if len(obs.others) else obs.poses
        s_all, lat_all = w.locate(everyone[:, 0], everyone[:, 1])
        s, lat = s_all[: len(x)], lat_all[: len(x)]
        ld = self.lookahead + self.k_v * np.maximum(obs.speeds, 0.0)
        target = w.centerline_pose(s + ld)
        tx = target[:, 0] - self.offsets * np.sin(target[:, 2])
        ty = target[:, 1] + self.offsets * np.cos(target[:, 2])
        alpha = np.arctan2(ty - y, tx - x) - yaw
        dist = np.hypot(tx - x, ty - y)
        delta = np.arctan2(2.0 * car.wheelbase * np.sin(alpha), np.maximum(dist, 1e-3))
        a_steer = np.clip(delta / car.steer_gain, -1.0, 1.0)
        a_thr = np.full(len(x), self.throttle)
        brake = np.zeros(len(x))
        for i in range(len(x)):
            ds = np.mod(s_all - s[i], w.length)
            same_way = np.cos(everyone[:, 2] - yaw[i]) > 0
            ahead = (ds > 1e-6) & (ds < self.gap_m) & same_way & (np.abs(lat_all - lat[i]) < self.lane_halfwidth)
            ahead[i] = False
            if ahead.any():
                a_thr[i] = 0.0
                brake[i] = float(ds[ahead].min() < self.brake_gap_m)
        return np.stack([a_thr, a_steer, brake], axis=1)


class CenterlineDriver:
    """Vectorised pure pursuit of the centerline, each car on its own lateral offset and at its
    own fraction of the obstacle top speed, slowing for curves and for a car ahead."""

    needs_lidar = False

    def __init__(self, a_lat: float = 3.0):
        """:param a_lat: lateral acceleration the speed profile allows in curves (m/s^2)."""
        self.a_lat = a_lat

    def __call__(self, fw) -> np.ndarray:  # fw: racecav.sim.fast_world.FastWorld
        K.pure_pursuit(fw.x, fw.y, fw.yaw, fw.v, fw.active, fw.cl_idx, fw.lane_offset, fw.vfac,
                       fw.cl, fw.cl_ds, fw.car.wheelbase, fw.car.steer_gain, fw.car.v_max,
                       self.a_lat, fw.car.width, 1, 1, fw._traffic_act)
        return fw._traffic_act[:, 1:]


class PolicyDriver(TrafficDriver):
    """Obstacle cars driven by a policy (e.g. the trained racing policy as a numpy MLP), each car
    on its own sanitized scan: ``policy(obs (B, n_rays)) -> actions (B, 2)``. Both backends."""

    needs_lidar = True

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray]):
        self.policy = policy

    def act(self, obs: TrafficObs) -> np.ndarray:  # PyBullet
        return np.asarray(self.policy(obs.scans), dtype=np.float64).reshape(-1, 2)

    def __call__(self, fw) -> np.ndarray:  # the fast world: every world's cars in one batch
        obs = fw.observations()[:, 1:]
        n, c, r = obs.shape
        return np.asarray(self.policy(obs.reshape(n * c, r)), dtype=np.float64).reshape(n, c, 2)


def make_driver(spec, backend: str = "bullet"):
    """The traffic driver of ``spec`` for ``backend`` ("bullet" or "fast").

    :param spec: None / "pure_pursuit" / "centerline" (the centerline follower), "policy:NAME_OR_PATH"
        (a shipped or exported policy, common/policy.py), a driver object (used as is) or a plain
        policy callable (wrapped in :class:`PolicyDriver`).
    :raises ValueError: naming an unknown driver or a policy file that cannot be loaded.
    """
    if backend not in ("bullet", "fast"):
        raise ValueError(f"backend: expected 'bullet' or 'fast', got {backend!r}")
    if spec is None or spec in ("pure_pursuit", "centerline"):
        return CenterlineDriver() if backend == "fast" else PurePursuitDriver()
    if isinstance(spec, str):
        if spec.startswith("policy:"):
            from racecav.common.policy import load_policy

            try:
                return PolicyDriver(load_policy(spec.split(":", 1)[1]))
            except (OSError, ValueError, KeyError) as e:
                raise ValueError(f"traffic.driver: cannot load {spec!r}: {e}") from None
        raise ValueError(f"traffic.driver: unknown driver {spec!r} (known: pure_pursuit = centerline, "
                         "policy:NAME_OR_PATH)")
    if hasattr(spec, "needs_lidar"):
        return spec
    if callable(spec):
        return PolicyDriver(spec)
    raise ValueError(f"traffic driver: expected a name or a callable, got {spec!r}")
