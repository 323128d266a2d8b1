"""The baseline's perception: obstacles and road boundary points from the same lidar scan the
policy sees, in the odometry frame.

1. Points: finite returns within ``max_range`` -> car frame (the lidar mount pose of the
   car file) -> odometry frame (the ego pose estimate at the scan's time).
2. Clustering: consecutive rays belong together while neighbouring points are closer than
   ``gap_m + gap_k * range * angle_increment`` (range-adaptive; up to ``max_skip`` rays without
   return may be bridged).
3. Classification: a cluster no longer than ``max_obstacle_extent`` (a car shows at most an L
   of 0.55 + 0.30 m), not cut off by the range limit, is an obstacle candidate; longer ones are
   walls/curbs. Each candidate gets free-space evidence: the fraction of its points that the
   previous scan saw through (its ray went farther): something moved in there.
4. Tracking: nearest-neighbour association of candidates to tracks (gated around the constant-
   velocity prediction), an alpha-beta filter for position and velocity (constant-velocity model);
   a track unseen while it should be visible is dropped after ``max_misses`` scans; one that left
   the field of view coasts for ``coast_s`` (it may still be beside the car).
5. Output: tracks seen ``confirm_hits`` times, faster than ``moving_speed`` and with
   ``dynamic_hits`` detections in previously free space are moving obstacles (predicted over the horizon by the MPC); the points of every other cluster (walls,
   curbs, parked cars, corners: whatever does not move) become static boundary points, evenly
   spaced along each cluster. A car standing still is thus avoided like a wall, and a wall
   fragment whose visible part slides as the ego moves (occlusion, field of view) cannot fake a
   moving obstacle: its new points were never seen free.
6. Memory: points of compact static objects that leave the field of view beside the ego are
   kept for ``memory_s`` (the 90 deg lidar is blind on the flanks, where a parked car is while
   the ego passes it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from racecav.common.config import PerceptionConfig
from racecav.common.vehicle import CarParams


@dataclass
class Track:
    """A tracked obstacle (odometry frame)."""

    id: int
    x: float
    y: float
    vx: float = 0.0
    vy: float = 0.0
    hits: int = 1
    misses: int = 0
    t: float = 0.0
    """Time (s) of the last update (scan clock)."""
    last_seen: float = 0.0
    extent: float = 0.0
    dynamic: int = 0
    """Detections that stood in previously free space."""
    moving: bool = False

    @property
    def speed(self) -> float:
        return float(np.hypot(self.vx, self.vy))


@dataclass
class Percept:
    """What one scan gives the MPC."""

    obstacles: list[Track] = field(default_factory=list)
    """Moving confirmed tracks, nearest first."""
    boundary: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """(M, 2) static boundary points (odometry frame), nearest first."""
    weight: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(M,) potential factor per boundary point: ``compact_weight`` for compact objects."""
    clusters: int = 0
    candidates: int = 0


def scan_points(ranges: np.ndarray, angles: np.ndarray, car: CarParams, max_range: float):
    """Car-frame points of the finite returns within ``max_range``: (points (N, 2), ray index (N,),
    range (N,))."""
    r = np.asarray(ranges, np.float64)
    ok = np.isfinite(r) & (r <= max_range) & (r > 0)
    idx = np.nonzero(ok)[0]
    m = car.lidar_mount
    a = angles[idx].astype(np.float64) + m.yaw
    pts = np.stack([m.x + r[idx] * np.cos(a), m.y + r[idx] * np.sin(a)], 1)
    return pts, idx, r[idx]


def cluster(points: np.ndarray, idx: np.ndarray, ranges: np.ndarray, angle_increment: float,
            p: PerceptionConfig) -> list[np.ndarray]:
    """Split consecutive returns into clusters; returns index arrays into ``points``."""
    if len(points) == 0:
        return []
    d = np.hypot(*(points[1:] - points[:-1]).T)
    thr = p.gap_m + p.gap_k * np.minimum(ranges[1:], ranges[:-1]) * angle_increment
    thr = thr * (idx[1:] - idx[:-1])  # a bridged gap of k rays allows k spacings
    brk = (d > thr) | (idx[1:] - idx[:-1] > p.max_skip + 1)
    starts = np.concatenate([[0], np.nonzero(brk)[0] + 1, [len(points)]])
    return [np.arange(a, b) for a, b in zip(starts[:-1], starts[1:])]


def to_frame(points: np.ndarray, pose) -> np.ndarray:
    """Car-frame points -> the frame in which the car has ``pose`` (x, y, yaw)."""
    x, y, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([x + c * points[:, 0] - s * points[:, 1], y + s * points[:, 0] + c * points[:, 1]], 1)


class Perception:
    """Clusters, classifies and tracks (see the module docstring).

    :param car: car parameters (lidar mount, lidar spec).
    :param params: tuning.
    """

    def __init__(self, car: CarParams, params: PerceptionConfig | None = None):
        self.car, self.p = car, params or PerceptionConfig()
        spec = car.lidar
        self.angles = (spec.angle_min + spec.angle_increment * np.arange(spec.n_rays)).astype(np.float64)
        self.half_fov = spec.fov / 2
        self.tracks: list[Track] = []
        self._next_id = 1
        self._prev = None
        self._memory = (np.zeros((0, 2)), np.zeros(0))

    def reset(self) -> None:
        self.tracks = []
        self._prev = None
        self._memory = (np.zeros((0, 2)), np.zeros(0))

    def detect(self, ranges: np.ndarray, pose) -> tuple[list[tuple[np.ndarray, float, float]], list[np.ndarray]]:
        """Obstacle candidates [(centre (2,), extent, free-space evidence)] and every cluster's
        evenly spaced points [(k, 2)] (candidate j is cluster ``self._cand_cluster[j]``), odometry
        frame."""
        p = self.p
        pts, idx, r = scan_points(ranges, self.angles, self.car, p.max_range)
        groups = cluster(pts, idx, r, self.car.lidar.angle_increment, p)
        cands, samples = [], []
        self._cand_cluster = []
        m = self.car.lidar_mount
        for gi, g in enumerate(groups):
            q = pts[g]
            extent = float(np.hypot(*(q.max(0) - q.min(0))))
            qw = to_frame(q, pose)
            # a cluster cut off by the range limit slides along with the ego: never a candidate
            if extent <= p.max_obstacle_extent and r[g].max() < p.max_range - 0.3:
                c = q.mean(0)
                ray = c - np.array([m.x, m.y])
                c = c + p.centre_offset * ray / max(np.linalg.norm(ray), 1e-6)
                cands.append((to_frame(c[None], pose)[0], extent, self._free_before(qw)))
                self._cand_cluster.append(gi)
            # evenly spaced along the cluster (arc length)
            s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(q, axis=0).T))])
            keep = np.searchsorted(s, np.arange(0.0, s[-1] + 1e-9, p.boundary_spacing))
            samples.append(qw[np.unique(np.minimum(keep, len(q) - 1))])
        self._prev = (np.asarray(ranges, np.float64), to_frame(np.array([[m.x, m.y]]), pose)[0],
                      pose[2] + m.yaw)
        return cands, samples

    def _free_before(self, points: np.ndarray) -> float:
        """Fraction of ``points`` (odometry frame) that the previous scan saw as free space: its
        ray in that direction went on beyond the point. Something standing there now moved in;
        a piece of wall appearing from behind an occluder (or entering the field of view) was
        not seen free before, so it gives no evidence of motion."""
        if self._prev is None:
            return 0.0
        prev, sensor, heading = self._prev
        d = points - sensor
        rng = np.hypot(d[:, 0], d[:, 1])
        ang = (np.arctan2(d[:, 1], d[:, 0]) - heading + np.pi) % (2 * np.pi) - np.pi
        spec = self.car.lidar
        k = np.rint((ang - spec.angle_min) / spec.angle_increment).astype(int)
        inside = (k >= 0) & (k < len(prev))
        if not inside.any():
            return 0.0
        before = prev[np.clip(k, 0, len(prev) - 1)]
        before = np.where(np.isfinite(before), before, np.inf)
        free = inside & (before > rng + self.p.free_margin)
        return float(free.sum()) / len(points)

    def _in_view(self, xy: np.ndarray, pose) -> np.ndarray:
        """Which odometry-frame points (k, 2) lie inside the lidar's field of view and range."""
        x, y, yaw = pose
        dx, dy = xy[:, 0] - x, xy[:, 1] - y
        fx = np.cos(yaw) * dx + np.sin(yaw) * dy - self.car.lidar_mount.x
        fy = -np.sin(yaw) * dx + np.cos(yaw) * dy
        return (np.abs(np.arctan2(fy, fx)) < self.half_fov - 0.05) & (np.hypot(fx, fy) < self.p.max_range)

    def _visible(self, tr: Track, pose) -> bool:
        """Whether a track's position lies inside the lidar's field of view and range."""
        return bool(self._in_view(np.array([[tr.x, tr.y]]), pose)[0])

    def _remember(self, compact: np.ndarray, pose, t: float) -> np.ndarray:
        """Points of compact static objects (a parked car, a corner; not long walls, which the
        ego drives along) seen now, plus those seen in the last ``memory_s`` that are now out of
        view beside the ego: a parked car beside the ego, outside the 90 deg field of view, still
        bounds it. Inside the view the current scan is authoritative."""
        mem, mem_t = self._memory
        if len(mem):
            x, y, yaw = pose
            ahead = np.cos(yaw) * (mem[:, 0] - x) + np.sin(yaw) * (mem[:, 1] - y)
            side = -np.sin(yaw) * (mem[:, 0] - x) + np.cos(yaw) * (mem[:, 1] - y)
            # only beside the ego (the blind flanks of a 90 deg lidar); behind its rear they
            # cannot be hit driving forward
            beside = (ahead > -self.car.length / 2) & (ahead < self.car.length) & (np.abs(side) < 1.0)
            keep = (t - mem_t <= self.p.memory_s) & ~self._in_view(mem, pose) & beside
            mem, mem_t = mem[keep], mem_t[keep]
        self._memory = (np.concatenate([compact, mem]), np.concatenate([np.full(len(compact), t), mem_t]))
        return self._memory[0]

    def update(self, ranges: np.ndarray, pose, t: float) -> Percept:
        """Process one scan.

        :param ranges: Scan ranges (+inf = no return).
        :param pose: ego pose (x, y, yaw) in the odometry frame at the scan's time.
        :param t: scan time (s, the scan's clock).
        """
        p = self.p
        cands, samples = self.detect(ranges, pose)
        # predict
        for tr in self.tracks:
            dt = t - tr.t
            tr.x += tr.vx * dt
            tr.y += tr.vy * dt
            tr.t = t
        # greedy nearest-neighbour association, closest pairs first
        pairs = []
        for i, tr in enumerate(self.tracks):
            for j, (c, _e, _f) in enumerate(cands):
                d = float(np.hypot(c[0] - tr.x, c[1] - tr.y))
                if d < p.gate_m:
                    pairs.append((d, i, j))
        used_t, used_c = set(), set()
        assoc: dict[int, int] = {}  # candidate -> track index
        for d, i, j in sorted(pairs):
            if i in used_t or j in used_c:
                continue
            used_t.add(i)
            used_c.add(j)
            assoc[j] = i
            tr, (c, e, free) = self.tracks[i], cands[j]
            dt = max(t - tr.last_seen, 1e-3)
            rx, ry = c[0] - tr.x, c[1] - tr.y
            if tr.hits == 1:  # second sighting: velocity from the two positions
                tr.vx, tr.vy = tr.vx + rx / dt, tr.vy + ry / dt
                tr.x, tr.y = c[0], c[1]
            else:
                tr.x += p.alpha * rx
                tr.y += p.alpha * ry
                tr.vx += p.beta * rx / dt
                tr.vy += p.beta * ry / dt
            sp = tr.speed
            if sp > p.max_speed:
                tr.vx, tr.vy = tr.vx * p.max_speed / sp, tr.vy * p.max_speed / sp
            tr.hits += 1
            tr.misses = 0
            tr.last_seen = t
            tr.extent = e
            tr.dynamic += free >= p.free_fraction
        for tr in self.tracks:  # hysteresis: a moving track stays moving until it is nearly still
            if tr.moving:
                tr.moving = tr.speed >= p.moving_speed / 2
            else:
                tr.moving = tr.hits >= p.confirm_hits and tr.speed >= p.moving_speed and tr.dynamic >= p.dynamic_hits
        moving_ids = {id(tr) for tr in self.tracks if tr.moving}
        moving_clusters = {self._cand_cluster[j] for j, i in assoc.items() if id(self.tracks[i]) in moving_ids}
        keep = []
        for i, tr in enumerate(self.tracks):
            if i not in used_t:
                if self._visible(tr, pose):
                    tr.misses += 1
                    if tr.misses > p.max_misses:
                        continue
                elif t - tr.last_seen > p.coast_s:
                    continue
            keep.append(tr)
        for j, (c, e, free) in enumerate(cands):
            if j not in used_c:
                keep.append(Track(self._next_id, float(c[0]), float(c[1]), t=t, last_seen=t, extent=e,
                                  dynamic=int(free >= p.free_fraction)))
                self._next_id += 1
        self.tracks = keep
        ex, ey = pose[0], pose[1]
        moving = [tr for tr in self.tracks if id(tr) in moving_ids]
        moving.sort(key=lambda tr: np.hypot(tr.x - ex, tr.y - ey))
        cand = set(self._cand_cluster)
        walls = [q for gi, q in enumerate(samples) if gi not in cand]
        compact = [samples[gi] for gi in self._cand_cluster if gi not in moving_clusters]
        walls = np.concatenate(walls) if walls else np.zeros((0, 2))
        compact = self._remember(np.concatenate(compact) if compact else np.zeros((0, 2)), pose, t)
        boundary = np.concatenate([walls, compact])
        weight = np.concatenate([np.ones(len(walls)), np.full(len(compact), p.compact_weight)])
        if len(boundary):
            order = np.argsort(np.hypot(boundary[:, 0] - ex, boundary[:, 1] - ey))
            boundary, weight = boundary[order], weight[order]
        return Percept(moving, boundary, weight, len(samples), len(cands))
