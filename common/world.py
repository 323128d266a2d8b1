"""The worlds (racetrack, intersection) as data, and the one place their geometry is generated.

A world file (common/data/worlds/NAME.toml) describes a track as pieces or roads; this module
turns it into wall segments, the single source of geometry: the PyBullet backend builds a box
per segment, the fast backend casts rays at them.

- ``kind = "loop"``: a closed lane given as a centerline of ``[[pieces]]`` from a start pose,
  each a straight (``straight = LENGTH``) or an arc (``arc_radius``, ``arc_deg``; positive =
  left turn). Walls are the exact offsets of the centerline by +-lane_width/2 (arcs subdivided
  at ``arc_max_step_deg``). The centerline direction is the traffic direction. A loop may cross
  itself (figure eight): the walls inside the other part of the lane are cut, the crossing is
  open.
- ``kind = "roads"``: straight ``[[roads]]`` (centre, yaw, length, width) and open ``[[ways]]``
  (a start pose, a width and straight / arc ``pieces`` as a loop's: roads of any shape, open at
  both ends); walls are the edges of every road and way minus the parts inside another road or
  way (the curbs of a crossing or a junction). No centerline.
Both accept extra ``[[walls]]`` segments (x0, y0, x1, y1). Units m, angles in files in degrees
(``*_deg``), everywhere in code in radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from racecav.common.vehicle import load_toml

WORLDS_DIR = Path(__file__).parent / "data" / "worlds"
CENTERLINE_STEP = 0.05
"""Spacing (m) of the sampled centerline used for progress and poses."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Piece(_Strict):
    """One piece of a loop: a straight or an arc (exactly one of the two)."""

    straight: float | None = Field(None, gt=0)
    arc_radius: float | None = Field(None, gt=0)
    arc_deg: float | None = None
    """Turn angle in degrees, positive = left (CCW)."""

    @model_validator(mode="after")
    def _one(self) -> "Piece":
        if (self.straight is None) == (self.arc_radius is None):
            raise ValueError("give either straight or arc_radius + arc_deg")
        if self.arc_radius is not None and not self.arc_deg:
            raise ValueError("arc_deg: required (non-zero) with arc_radius")
        return self


class Road(_Strict):
    cx: float
    cy: float
    yaw_deg: float
    length: float = Field(gt=0)
    width: float = Field(gt=0)


class Way(_Strict):
    """An open road of any shape: from a start pose (its centre line's first point and
    heading), ``pieces`` of straights and arcs as a loop's, ``width`` curb to curb."""

    x: float
    y: float
    yaw_deg: float
    width: float = Field(gt=0)
    pieces: list[Piece] = Field(min_length=1)


class Pose2(_Strict):
    x: float = 0.0
    y: float = 0.0
    yaw_deg: float = 0.0


class WorldFile(_Strict):
    """Schema of a world file."""

    name: str
    kind: Literal["loop", "roads"]
    description: str = ""
    wall_thickness: float = Field(0.1, gt=0)
    wall_height: float = Field(0.3, gt=0)
    lane_width: float = Field(gt=0)
    """loop: width between the walls; roads: the road width (informational)."""
    arc_max_step_deg: float = Field(10.0, gt=0, le=45)
    start: Pose2 = Pose2()
    pieces: list[Piece] = []
    roads: list[Road] = []
    ways: list[Way] = []
    walls: list[tuple[float, float, float, float]] = []
    closure_tolerance: float = Field(0.01, gt=0)

    @model_validator(mode="after")
    def _check(self) -> "WorldFile":
        if self.kind == "loop" and not self.pieces:
            raise ValueError("pieces: a loop needs at least one piece")
        if self.kind == "roads" and not (self.roads or self.ways):
            raise ValueError("roads: a roads world needs at least one road or way")
        if self.kind == "loop" and self.ways:
            raise ValueError("ways: only in a roads world")
        for i, p in enumerate(self.pieces):
            if p.arc_radius is not None and p.arc_radius <= self.lane_width / 2:
                raise ValueError(f"pieces.{i}.arc_radius: must exceed lane_width / 2")
        for i, w in enumerate(self.ways):
            for j, p in enumerate(w.pieces):
                if p.arc_radius is not None and p.arc_radius <= w.width / 2:
                    raise ValueError(f"ways.{i}.pieces.{j}.arc_radius: must exceed the way's width / 2")
        return self


@dataclass(frozen=True)
class World:
    """A world ready for a backend. Arrays are read-only."""

    name: str
    kind: str
    walls: np.ndarray
    """float32 (M, 4): segments x0, y0, x1, y1 in the world frame (wall centre lines)."""
    wall_thickness: float
    wall_height: float
    lane_width: float
    centerline: np.ndarray | None
    """float32 (K, 2), closed loop (last point != first), traffic direction; None for roads."""
    description: str = ""
    _s: np.ndarray | None = field(default=None, repr=False)
    _cl64: np.ndarray | None = field(default=None, repr=False)

    @property
    def length(self) -> float:
        """Centerline length (m) of a loop."""
        self._need_centerline()
        return float(self._s[-1])

    def _need_centerline(self) -> None:
        if self.centerline is None:
            raise ValueError(f"world {self.name!r} has no centerline (kind {self.kind})")

    def centerline_pose(self, s) -> np.ndarray:
        """Pose(s) on the centerline at arc length ``s`` (wraps around): (..., 3) x, y, yaw."""
        self._need_centerline()
        pts = np.vstack([self.centerline, self.centerline[:1]]).astype(np.float64)
        s = np.mod(np.asarray(s, dtype=np.float64), self.length)
        i = np.clip(np.searchsorted(self._s, s, side="right") - 1, 0, len(pts) - 2)
        t = (s - self._s[i]) / np.maximum(self._s[i + 1] - self._s[i], 1e-12)
        p0, p1 = pts[i], pts[i + 1]
        xy = p0 + (p1 - p0) * t[..., None]
        yaw = np.arctan2(p1[..., 1] - p0[..., 1], p1[..., 0] - p0[..., 0])
        return np.concatenate([xy, yaw[..., None]], axis=-1)

    def locate(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Arc length s (m, in [0, length)) of the closest centerline point, and the signed
        lateral offset (m, positive = left of the traffic direction), for points (x, y)."""
        self._need_centerline()
        cl = self._cl64
        q = np.stack([np.atleast_1d(np.asarray(x, np.float64)), np.atleast_1d(np.asarray(y, np.float64))], -1)
        d2 = ((q[:, None, :] - cl[None, :, :]) ** 2).sum(-1)
        k = d2.argmin(1)
        n = len(cl)
        best_s = np.empty(len(q))
        best_lat = np.empty(len(q))
        best_d = np.full(len(q), np.inf)
        for i0 in ((k - 1) % n, k):  # the two segments around the nearest vertex
            a, b = cl[i0], cl[(i0 + 1) % n]
            d = b - a
            seg2 = (d * d).sum(-1)
            t = np.clip(((q - a) * d).sum(-1) / seg2, 0.0, 1.0)
            foot = a + d * t[:, None]
            dist = ((q - foot) ** 2).sum(-1)
            better = dist < best_d
            seg = np.sqrt(seg2)
            cross = (d[:, 0] * (q[:, 1] - a[:, 1]) - d[:, 1] * (q[:, 0] - a[:, 0])) / seg
            best_s = np.where(better, self._s[i0] + t * seg, best_s)
            best_lat = np.where(better, cross, best_lat)
            best_d = np.where(better, dist, best_d)
        shape = np.shape(x)
        return np.mod(best_s, self.length).reshape(shape), best_lat.reshape(shape)

    def progress(self, x, y) -> np.ndarray:
        """Arc length (m, in [0, length)) of the centerline point closest to (x, y)."""
        return self.locate(x, y)[0]

    def lateral_offset(self, x, y) -> np.ndarray:
        """Signed distance (m, positive = left of the traffic direction) from the centerline."""
        return self.locate(x, y)[1]

    def start_poses(self, n: int, rng: np.random.Generator, spacing: float | None = None,
                    lateral: float | None = None, s0: float | None = None) -> np.ndarray:
        """Spread ``n`` cars along the centerline, facing the traffic direction.

        :param spacing: arc length between consecutive cars (default: evenly over the loop).
        :param lateral: max |lateral offset| (default a quarter of the lane width), uniform.
        :param s0: arc length of the first car (default uniform random).
        :return: float64 (n, 3) x, y, yaw.
        """
        self._need_centerline()
        spacing = self.length / max(n, 1) if spacing is None else spacing
        if spacing * n > self.length:
            raise ValueError(f"spacing: {n} cars x {spacing} m do not fit on {self.length:.1f} m")
        lateral = self.lane_width / 4 if lateral is None else lateral
        s0 = rng.uniform(0, self.length) if s0 is None else s0
        s = s0 + spacing * np.arange(n)
        pose = self.centerline_pose(s)
        off = rng.uniform(-lateral, lateral, n)
        pose[:, 0] -= off * np.sin(pose[:, 2])
        pose[:, 1] += off * np.cos(pose[:, 2])
        return pose


def _loop_geometry(f: WorldFile) -> tuple[np.ndarray, np.ndarray]:
    """Walls (M, 4) and centerline (K, 2) of a loop from its pieces."""
    x, y, h = f.start.x, f.start.y, math.radians(f.start.yaw_deg)
    half = f.lane_width / 2
    center: list[tuple[float, float]] = [(x, y)]
    left: list[tuple[float, float]] = []
    right: list[tuple[float, float]] = []
    station: list[float] = []  # arc length of the centerline point each wall vertex belongs to
    s_here = 0.0

    def edge(px: float, py: float, hh: float) -> None:
        left.append((px - half * math.sin(hh), py + half * math.cos(hh)))
        right.append((px + half * math.sin(hh), py - half * math.cos(hh)))
        station.append(s_here)

    edge(x, y, h)
    for p in f.pieces:
        if p.straight is not None:
            n_c = max(1, math.ceil(p.straight / CENTERLINE_STEP))
            for k in range(1, n_c + 1):
                center.append((x + p.straight * k / n_c * math.cos(h), y + p.straight * k / n_c * math.sin(h)))
            x, y = center[-1]
            s_here += p.straight
            edge(x, y, h)
        else:
            r, turn = p.arc_radius, math.radians(p.arc_deg)
            sgn = 1.0 if turn > 0 else -1.0
            cx, cy = x - sgn * r * math.sin(h), y + sgn * r * math.cos(h)
            n_c = max(1, math.ceil(r * abs(turn) / CENTERLINE_STEP))
            n_w = max(1, math.ceil(abs(p.arc_deg) / f.arc_max_step_deg))

            def at(frac: float) -> tuple[float, float, float]:
                hh = h + turn * frac
                return cx + sgn * r * math.sin(hh), cy - sgn * r * math.cos(hh), hh

            for k in range(1, n_c + 1):
                center.append(at(k / n_c)[:2])
            s0 = s_here
            for k in range(1, n_w + 1):
                s_here = s0 + r * abs(turn) * k / n_w
                edge(*at(k / n_w))
            x, y, h = at(1.0)
    gap = math.hypot(x - f.start.x, y - f.start.y)
    dh = (h - math.radians(f.start.yaw_deg) + math.pi) % (2 * math.pi) - math.pi
    if gap > f.closure_tolerance or abs(dh) > 1e-6:
        raise ValueError(f"pieces: the loop does not close (end is {gap:.3f} m and "
                         f"{math.degrees(dh):.2f} deg from the start)")
    segs, seg_s = [], []
    for side in (left, right):
        side[-1] = side[0]  # close exactly (the end matches the start within tolerance)
        for k, (a, b) in enumerate(zip(side[:-1], side[1:])):
            segs.append((*a, *b))
            seg_s.append((station[k], station[k + 1]))
    cl = np.asarray(center[:-1], dtype=np.float64)
    return _cut_crossings(np.asarray(segs, dtype=np.float64), np.asarray(seg_s), cl, half), cl


CROSSING_CUT_STEP = 0.005
"""m: resolution of the wall ends at a crossing of a self-crossing loop (figure eight)."""


def _cut_crossings(segs: np.ndarray, seg_s: np.ndarray, cl: np.ndarray, half: float) -> np.ndarray:
    """Remove the parts of the walls that lie inside another part of the lane (a loop crossing
    itself, e.g. a figure eight: the crossing is open, like the roads of an intersection).

    A wall point is inside another part of the lane when it is closer than ``half`` to a stretch
    of the centerline more than a lane width away (along the loop) from the point's own station
    (``seg_s``: the stations of each segment's ends). Tracks that do not cross themselves come
    out unchanged.
    """
    pts = np.vstack([cl, cl[:1]])
    a, d = pts[:-1], np.diff(pts, axis=0)
    seg_len = np.linalg.norm(d, axis=1)
    s_cl = np.concatenate([[0.0], np.cumsum(seg_len)])[:-1]
    lap = float(seg_len.sum())

    lo, hi = np.minimum(a, a + d), np.maximum(a, a + d)  # bounding box of each centerline segment

    def nearest(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point: distance to the centerline segments (Q, K') and their stations. Only the
        K' segments whose bounding box comes within ``half`` of the points' box: the others are
        farther than ``half`` from every point and cannot make one inside (exact, and it keeps
        building a world fast: every env and test builds one)."""
        near = np.all((lo <= q.max(0) + half) & (hi >= q.min(0) - half), axis=1)
        a_, d_, len_ = a[near], d[near], seg_len[near]
        t = np.clip(((q[:, None, :] - a_[None]) * d_[None]).sum(-1) / np.maximum(len_**2, 1e-12), 0, 1)
        dist = np.linalg.norm(a_[None] + d_[None] * t[..., None] - q[:, None, :], axis=-1)
        return dist, s_cl[near][None, :] + t * len_[None, :]

    out = []
    for (x0, y0, x1, y1), (sa, sb) in zip(segs, seg_s):
        n = max(2, int(math.ceil(math.hypot(x1 - x0, y1 - y0) / CROSSING_CUT_STEP)) + 1)
        u = np.linspace(0.0, 1.0, n)
        q = np.stack([x0 + (x1 - x0) * u, y0 + (y1 - y0) * u], -1)
        dist, s = nearest(q)
        own = sa + (sb - sa) * u
        gap = np.abs((s - own[:, None] + lap / 2) % lap - lap / 2)
        inside = ((dist < half - 1e-6) & (gap > 2 * half)).any(1)
        if not inside.any():
            out.append((x0, y0, x1, y1))
            continue
        # keep the runs of outside points, ends snapped to the first/last outside sample
        k = 0
        while k < n:
            if inside[k]:
                k += 1
                continue
            j = k
            while j + 1 < n and not inside[j + 1]:
                j += 1
            if j > k:
                out.append((*q[k], *q[j]))
            k = j + 1
    return np.asarray(out, dtype=np.float64).reshape(-1, 4)


def way_edges(w: Way, step_deg: float) -> tuple[list, list]:
    """Left and right edge polylines of an open way (arcs subdivided at ``step_deg``)."""
    x, y, h = w.x, w.y, math.radians(w.yaw_deg)
    half = w.width / 2
    left: list[tuple[float, float]] = []
    right: list[tuple[float, float]] = []

    def edge(px: float, py: float, hh: float) -> None:
        left.append((px - half * math.sin(hh), py + half * math.cos(hh)))
        right.append((px + half * math.sin(hh), py - half * math.cos(hh)))

    edge(x, y, h)
    for p in w.pieces:
        if p.straight is not None:
            x, y = x + p.straight * math.cos(h), y + p.straight * math.sin(h)
            edge(x, y, h)
            continue
        r, turn = p.arc_radius, math.radians(p.arc_deg)
        sgn = 1.0 if turn > 0 else -1.0
        cx, cy = x - sgn * r * math.sin(h), y + sgn * r * math.cos(h)
        n_w = max(1, math.ceil(abs(p.arc_deg) / step_deg))
        for k in range(1, n_w + 1):
            hh = h + turn * k / n_w
            edge(cx + sgn * r * math.sin(hh), cy - sgn * r * math.cos(hh), hh)
        h = h + turn
        x, y = cx + sgn * r * math.sin(h), cy - sgn * r * math.cos(h)
    return left, right


def _road_quad(r: Road) -> np.ndarray:
    c, s = math.cos(math.radians(r.yaw_deg)), math.sin(math.radians(r.yaw_deg))
    u, v = np.array([c, s]) * r.length / 2, np.array([-s, c]) * r.width / 2
    ctr = np.array([r.cx, r.cy])
    return np.array([ctr - u - v, ctr + u - v, ctr + u + v, ctr - u + v])


def _road_walls(f: WorldFile) -> np.ndarray:
    """Road and way edges minus the parts inside another road or way (the curbs of a crossing or
    a junction). A way's area is the union of the quadrilaterals between consecutive vertices of
    its two edges (its arcs as the chords its curbs are)."""
    # each road or way: its curb segments and the convex areas (quads) that cut the others' curbs
    items: list[tuple[list, list[np.ndarray]]] = []
    for r in f.roads:
        c, s = math.cos(math.radians(r.yaw_deg)), math.sin(math.radians(r.yaw_deg))
        curbs = []
        for side in (-1, 1):
            ox, oy = r.cx - side * r.width / 2 * s, r.cy + side * r.width / 2 * c
            curbs.append((np.array([ox - r.length / 2 * c, oy - r.length / 2 * s]),
                          np.array([r.length * c, r.length * s])))
        items.append((curbs, [_road_quad(r)]))
    for w in f.ways:
        left, right = way_edges(w, f.arc_max_step_deg)
        curbs = [(np.array(a), np.array(b) - np.array(a)) for side in (left, right)
                 for a, b in zip(side[:-1], side[1:])]
        quads = [np.array([right[k], right[k + 1], left[k + 1], left[k]]) for k in range(len(left) - 1)]
        items.append((curbs, quads))
    segs = []
    for i, (curbs, _) in enumerate(items):
        for a, d in curbs:
            cuts = [(0.0, 1.0)]
            for j, (_, quads) in enumerate(items):
                if j == i:
                    continue
                for q in quads:
                    lo, hi = _clip_to_quad(a, d, q)
                    if lo < hi:
                        cuts = [piece for (u, v) in cuts for piece in ((u, min(v, lo)), (max(u, hi), v))
                                if piece[1] - piece[0] > 1e-9]
            for u, v in cuts:
                p0, p1 = a + d * u, a + d * v
                segs.append((p0[0], p0[1], p1[0], p1[1]))
    return np.asarray(segs, dtype=np.float64).reshape(-1, 4)


def _clip_to_quad(a: np.ndarray, d: np.ndarray, quad: np.ndarray) -> tuple[float, float]:
    """Parameter interval [lo, hi] of a + t d (t in [0, 1]) inside a convex quadrilateral
    (Cyrus-Beck; either vertex order)."""
    area = sum(quad[k, 0] * quad[(k + 1) % 4, 1] - quad[(k + 1) % 4, 0] * quad[k, 1] for k in range(4))
    if abs(area) < 1e-12:
        return 1.0, 0.0
    orient = 1.0 if area > 0 else -1.0
    lo, hi = 0.0, 1.0
    for k in range(4):
        p, e = quad[k], quad[(k + 1) % 4] - quad[k]
        n = orient * np.array([e[1], -e[0]])  # outward normal
        num = float(n @ (a - p))
        den = float(n @ d)
        if abs(den) < 1e-12:
            if num > 0:
                return 1.0, 0.0
            continue
        t = -num / den
        if den > 0:
            hi = min(hi, t)
        else:
            lo = max(lo, t)
    return lo, hi


def build_world(f: WorldFile) -> World:
    """Generate a World's geometry from its validated file (the only geometry generator)."""
    if f.kind == "loop":
        walls, cl = _loop_geometry(f)
    else:
        walls, cl = _road_walls(f), None
    if f.walls:
        walls = np.vstack([walls, np.asarray(f.walls, dtype=np.float64)])
    walls = walls.astype(np.float32)
    walls.setflags(write=False)
    s = None
    if cl is not None:
        pts = np.vstack([cl, cl[:1]])
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        cl = cl.astype(np.float32)
        cl.setflags(write=False)
    return World(name=f.name, kind=f.kind, walls=walls, wall_thickness=f.wall_thickness,
                 wall_height=f.wall_height, lane_width=f.lane_width, centerline=cl,
                 description=f.description, _s=s,
                 _cl64=None if cl is None else cl.astype(np.float64))


def load_world(name_or_path: str | Path = "racetrack") -> World:
    """Load a world by name (common/data/worlds/NAME.toml) or from a TOML file path.

    :raises ValueError: naming the file and the invalid field.
    """
    f = load_toml(name_or_path, WORLDS_DIR, WorldFile, "world")
    try:
        return build_world(f)
    except ValueError as e:
        raise ValueError(f"world file {name_or_path}: {e}") from None


def segment_distance(px, py, walls: np.ndarray) -> np.ndarray:
    """Distance from points (N,) to the nearest wall segment centre line: float64 (N,)."""
    p = np.stack([np.asarray(px, np.float64), np.asarray(py, np.float64)], -1)[:, None, :]
    a, b = walls[None, :, :2].astype(np.float64), walls[None, :, 2:].astype(np.float64)
    d = b - a
    t = np.clip(((p - a) * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0, 1)
    return np.sqrt((((a + d * t[..., None]) - p) ** 2).sum(-1)).min(-1)


def plot_world(world: World, ax=None, show_centerline: bool = True):
    """Draw a world's walls (and centerline) on a matplotlib axis; returns the axis."""
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(figsize=(10, 5))
    for x0, y0, x1, y1 in world.walls:
        ax.plot([x0, x1], [y0, y1], "k-", lw=1.5)
    if show_centerline and world.centerline is not None:
        cl = np.vstack([world.centerline, world.centerline[:1]])
        ax.plot(cl[:, 0], cl[:, 1], "b:", lw=1, label="centerline (traffic direction)")
        ax.annotate("", xy=cl[40], xytext=cl[0], arrowprops=dict(arrowstyle="->", color="b"))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(world.name)
    return ax
