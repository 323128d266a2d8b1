"""The baseline's perception: obstacles and road boundary points from the same lidar scan the
policy sees, in the odometry frame.

1. Points: finite returns within ``perception_range`` -> car frame (the lidar mount pose of the
   car file) -> odometry frame (the ego pose estimate at the scan's time).
2. Clustering: consecutive rays belong together while neighbouring points are closer than
   ``gap_m + gap_k * range * angle_increment`` (range-adaptive; up to ``max_skip`` rays without
   return may be bridged).
3. Classification by size: a cluster no longer than ``max_obstacle_extent`` is an obstacle
   candidate (a car shows at most an L of 0.55 + 0.30 m); longer clusters are walls/curbs.
4. Tracking: nearest-neighbour association of candidates to tracks (gated around the constant-
   velocity prediction), an alpha-beta filter for position and velocity (constant-velocity model);
   a track unseen while it should be visible is dropped after ``max_misses`` scans; one that left
   the field of view coasts for ``coast_s`` (it may still be beside the car).
5. Output: tracks seen ``confirm_hits`` times and faster than ``moving_speed`` are moving
   obstacles (predicted over the horizon by the MPC); the points of every other cluster (walls,
   curbs, parked cars, corners: whatever does not move) become static boundary points, evenly
   spaced along each cluster. A car standing still is thus avoided like a wall, and centroid
   jitter of a wall fragment (its visible part changes as the ego moves) cannot fake a fast
   obstacle unless it persists.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from racecav.common.vehicle import CarParams


@dataclass
class PerceptionParams:
    """Tuning of the perception (defaults suit the 1/10 car and its lidar)."""

    max_range: float = 6.0
    """Returns farther than this (m) are ignored."""
    gap_m: float = 0.12
    """Constant part of the clustering distance threshold (m)."""
    gap_k: float = 3.0
    """Range-proportional part: this many ray spacings at the point's range."""
    max_skip: int = 2
    """Rays without return that may lie inside one cluster."""
    max_obstacle_extent: float = 0.8
    """Clusters longer than this (m, first to last point / bounding diagonal) are boundary."""
    centre_offset: float = 0.1
    """The lidar sees a car's near side: its centre lies this far (m) behind the visible points."""
    boundary_spacing: float = 0.15
    """Spacing (m) of the boundary points taken from long clusters."""
    gate_m: float = 0.5
    """Association gate (m) around a track's predicted position."""
    alpha: float = 0.5
    """Alpha-beta filter position gain."""
    beta: float = 0.2
    """Alpha-beta filter velocity gain."""
    max_speed: float = 4.0
    """Velocity estimates are clipped to this (m/s): association glitches must not fling tracks."""
    confirm_hits: int = 3
    moving_speed: float = 0.5
    """m/s: a confirmed track at least this fast is a moving obstacle; slower ones are static."""
    max_misses: int = 3
    coast_s: float = 1.0


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
            p: PerceptionParams) -> list[np.ndarray]:
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

    def __init__(self, car: CarParams, params: PerceptionParams | None = None):
        self.car, self.p = car, params or PerceptionParams()
        spec = car.lidar
        self.angles = (spec.angle_min + spec.angle_increment * np.arange(spec.n_rays)).astype(np.float64)
        self.half_fov = spec.fov / 2
        self.tracks: list[Track] = []
        self._next_id = 1

    def reset(self) -> None:
        self.tracks = []

    def detect(self, ranges: np.ndarray, pose) -> tuple[list[tuple[np.ndarray, float]], list[np.ndarray]]:
        """Obstacle candidates [(centre (2,), extent)] and every cluster's evenly spaced points
        [(k, 2)] (index-aligned: candidate j is cluster ``self._cand_cluster[j]``), odometry frame."""
        p = self.p
        pts, idx, r = scan_points(ranges, self.angles, self.car, p.max_range)
        groups = cluster(pts, idx, r, self.car.lidar.angle_increment, p)
        cands, samples = [], []
        self._cand_cluster = []
        m = self.car.lidar_mount
        for gi, g in enumerate(groups):
            q = pts[g]
            extent = float(np.hypot(*(q.max(0) - q.min(0))))
            # a cluster cut off by the range limit slides along with the ego: never a candidate
            if extent <= p.max_obstacle_extent and r[g].max() < p.max_range - 0.3:
                c = q.mean(0)
                ray = c - np.array([m.x, m.y])
                c = c + p.centre_offset * ray / max(np.linalg.norm(ray), 1e-6)
                cands.append((to_frame(c[None], pose)[0], extent))
                self._cand_cluster.append(gi)
            # evenly spaced along the cluster (arc length)
            s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(q, axis=0).T))])
            keep = np.searchsorted(s, np.arange(0.0, s[-1] + 1e-9, p.boundary_spacing))
            samples.append(to_frame(q[np.unique(np.minimum(keep, len(q) - 1))], pose))
        return cands, samples

    def _visible(self, tr: Track, pose) -> bool:
        """Whether a track's position lies inside the lidar's field of view and range."""
        x, y, yaw = pose
        dx, dy = tr.x - x, tr.y - y
        fx, fy = np.cos(yaw) * dx + np.sin(yaw) * dy, -np.sin(yaw) * dx + np.cos(yaw) * dy
        fx -= self.car.lidar_mount.x
        ang = np.arctan2(fy, fx)
        return abs(ang) < self.half_fov - 0.05 and np.hypot(fx, fy) < self.p.max_range

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
            for j, (c, _e) in enumerate(cands):
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
            tr, (c, e) = self.tracks[i], cands[j]
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
        moving_ids = {id(tr) for tr in self.tracks if tr.hits >= p.confirm_hits and tr.speed >= p.moving_speed}
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
        for j, (c, e) in enumerate(cands):
            if j not in used_c:
                keep.append(Track(self._next_id, float(c[0]), float(c[1]), t=t, last_seen=t, extent=e))
                self._next_id += 1
        self.tracks = keep
        ex, ey = pose[0], pose[1]
        moving = [tr for tr in self.tracks if id(tr) in moving_ids]
        moving.sort(key=lambda tr: np.hypot(tr.x - ex, tr.y - ey))
        static = [q for gi, q in enumerate(samples) if gi not in moving_clusters]
        boundary = np.concatenate(static) if static else np.zeros((0, 2))
        if len(boundary):
            boundary = boundary[np.argsort(np.hypot(boundary[:, 0] - ex, boundary[:, 1] - ey))]
        return Percept(moving, boundary, len(samples), len(cands))
