"""Drivers of the obstacle cars lapping the racetrack (pluggable).

A driver sees every car (poses, speeds and, if it asks for them, lidar observations) and returns
normalised actions (a_T, a_delta) for the obstacle cars, which go through the same actuation
(:mod:`racecav.common.vehicle`) as the agent. The centerline pure-pursuit driver ships now; the
trained racing policy plugs in as another :class:`TrafficDriver` (``needs_lidar = True``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from racecav.common.vehicle import CarParams
from racecav.common.world import World


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


class PolicyDriver(TrafficDriver):
    """Obstacle cars driven by a trained policy (the paper's racing policy): each car acts on its
    own sanitized 170-ray scan, like the agent."""

    needs_lidar = True

    def __init__(self, policy):
        """:param policy: callable ``obs (n, n_rays) -> actions (n, 2)`` in [-1, 1]."""
        self.policy = policy

    def act(self, obs: TrafficObs) -> np.ndarray:
        return np.asarray(self.policy(obs.scans), dtype=np.float64).reshape(-1, 2)


DRIVERS = {"pure_pursuit": PurePursuitDriver, "centerline": PurePursuitDriver}


def make_driver(name: str) -> TrafficDriver:
    """A traffic driver by name (the scenario's ``traffic.driver``): a key of DRIVERS, or
    ``policy:NAME_OR_PATH`` for a shipped or exported policy (racecav.training.policy_io)."""
    if name.startswith("policy:"):
        from racecav.training.policy_io import load_numpy_policy

        try:
            return PolicyDriver(load_numpy_policy(name.split(":", 1)[1]))
        except (OSError, ValueError, KeyError) as e:
            raise ValueError(f"traffic.driver: cannot load {name!r}: {e}") from None
    try:
        return DRIVERS[name]()
    except KeyError:
        raise ValueError(f"traffic.driver: unknown driver {name!r} (known: {sorted(DRIVERS)} "
                         "or policy:NAME_OR_PATH)") from None
