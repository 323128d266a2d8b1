"""``racecav suite generate --name roads``: the generalization benchmark, procedural worlds and
behaviours drawn from a suite file (common/data/suites/roads.toml, fields in docs/world.md).

Every generated scenario carries its world inline (``[map]``: the ego's straight road and the
roads or ways of its shape), so a file's digest covers the road it is played on. The ego always
drives along +x in its right-hand lane, on a straight road, towards its conflict point at x = 0
(the junction), so the two straight references stay meaningful.

- shapes: ``straight`` (the ego's road alone), ``cross`` (a second road crossing at an angle),
  ``t`` (a side road from either side), ``y`` (a shallow branch, forward or backward, either
  side), ``bend`` (a side road that comes round a bend and crosses);
- conflict families (a behaviour each): crossing, braking, turn-across, merge, cut-in, hidden,
  head-on, multi, rear-stationary, rear-slow, rear-braking; timed by the ego as the conflict
  suite's (start trigger on its time to arrival + synchronised arrival, sim/actors.py);
- control families: stop-short, turn-away, pass-ahead, pass-behind, oncoming, parked, from-rest.

Validation on the fast world: a conflict must make both non-evading references (straight at
1 m/s and at full throttle; CHECK_TRIALS randomised trials each, the ego's start also shifted
5 cm to either side) collide every time, and both must pass it with its conflicting actors taken
out; a control must be passed by both every time. A draw that fails is redrawn (counted in the
manifest).

Splits: train (conflicts + controls), test (disjoint seeds), ood (conflicts; each file draws one
parameter from a band declared held out in ``[ood]``, which train and test never draw) and
controls (fresh seeds). Output: runs/suites/NAME/{train,test,ood,controls}/*.toml and suite.json.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from racecav.common.scenario import Scenario
from racecav.common.vehicle import load_car, load_toml
from racecav.evaluation.suite import Range, _check_ranges, _pt, _r, _Strict

SUITES_DIR = Path(__file__).resolve().parent.parent / "common" / "data" / "suites"
SPLITS = ("train", "test", "ood", "controls")
SHAPES = ("straight", "cross", "t", "y", "bend")
CONFLICTS = ("crossing", "braking", "turn_across", "merge", "cut_in", "hidden", "head_on", "multi",
             "rear_stationary", "rear_slow", "rear_braking")
CONTROLS = ("stop_short", "turn_away", "pass_ahead", "pass_behind", "oncoming", "parked", "from_rest")
CHECK_TRIALS = 4
VALIDATION_SHIFTS = (0.0, -0.05, 0.05)
REFERENCE_SPEEDS = (1.0, None)
PASSED_M = 0.5
MAX_ATTEMPTS = 400
ROAD_LENGTH = 30.0
SIDE_LENGTH = 9.0
_CAR = load_car()
CAR_L, CAR_W = _CAR.length, _CAR.width


class Common(_Strict):
    width_m: Range = (1.6, 3.2)
    """Road width (every road of a map)."""
    angle_deg: Range = (20.0, 160.0)
    """Crossing angle of a crossing road (cross, bend), from the ego's heading."""
    t_angle_deg: Range = (60.0, 120.0)
    y_angle_deg: Range = (20.0, 40.0)
    bend_deg: Range = (30.0, 75.0)
    bend_radius_m: Range = (2.0, 4.0)
    actor_speed: Range = (0.2, 3.0)
    """Every moving actor's nominal speed and its synchronised speed's clamp."""
    ego_distance_m: Range = (4.0, 6.5)
    ego_speed: Range = (0.8, 1.4)
    rest_distance_m: Range = (2.0, 6.0)
    actor_distance_m: Range = (2.5, 5.0)
    turn_radius_m: Range = (0.6, 1.2)
    release_time_s: Range = (0.6, 1.0)
    release_distance_m: Range = (0.8, 1.2)
    release_stopped_s: float | None = Field(1.0, ge=0)
    """A synchronised actor goes on at its nominal speed once the ego has stood still this long
    (an ego that yields is not kept waiting by an actor crawling at its minimum speed)."""
    ttc_s: Range = (1.5, 3.0)
    overlap: Range = (-0.75, 1.0)
    lead_decel: Range = (2.0, 6.0)
    headway_m: Range = (1.2, 4.0)
    margin_s: float = Field(3.0, ge=0)
    progress_past_m: float = Field(1.5, ge=0)

    @model_validator(mode="after")
    def _check(self) -> "Common":
        _check_ranges(self)
        if self.width_m[0] < 1.2:
            raise ValueError("width_m: at least 1.2 m (two lanes of a car)")
        if not 0 < self.angle_deg[0] <= self.angle_deg[1] < 180:
            raise ValueError("angle_deg: within (0, 180)")
        if self.actor_speed[0] <= 0:
            raise ValueError("actor_speed: must be positive")
        return self


class Ood(_Strict):
    """Held-out bands: train and test never draw them; each ood file draws one of them."""

    shapes: list[Literal[SHAPES]] = []
    angle_deg: list[Range] = []
    width_m: list[Range] = []
    actor_speed: list[Range] = []

    @model_validator(mode="after")
    def _check(self) -> "Ood":
        for name in ("angle_deg", "width_m", "actor_speed"):
            for r in getattr(self, name):
                if r[0] >= r[1]:
                    raise ValueError(f"{name}: band {list(r)} must have low < high")
        return self


class BFamily(_Strict):
    name: str = Field(pattern=r"^[a-z0-9][a-z0-9-]*$")
    behaviour: Literal[CONFLICTS + CONTROLS]
    shapes: list[Literal[SHAPES]] = Field(min_length=1)

    @property
    def control(self) -> bool:
        return self.behaviour in CONTROLS


ALLOWED = {"crossing": {"cross", "bend"}, "braking": {"cross", "bend", "t", "y"},
           "turn_across": {"cross", "t", "y"}, "merge": {"t", "y"}, "cut_in": {"straight", "cross", "t"},
           "hidden": {"cross"}, "head_on": {"straight", "cross", "t"}, "multi": {"cross"},
           "rear_stationary": {"straight", "cross", "t"}, "rear_slow": {"straight"}, "rear_braking": {"straight"},
           "stop_short": {"cross", "bend", "t", "y"}, "turn_away": {"cross", "t", "y"},
           "pass_ahead": {"cross", "bend"}, "pass_behind": {"cross", "bend"},
           "oncoming": {"straight", "cross", "t"}, "parked": {"straight", "cross", "t"},
           "from_rest": {"straight", "cross", "t", "y", "bend"}}
"""The shapes each behaviour can be drawn on."""


class BenchmarkFile(_Strict):
    name: str
    generator: Literal["roads"]
    description: str = ""
    n_test: int = Field(10, ge=1)
    """Files per family in test, ood and controls."""
    n_train: int = Field(40, ge=1)
    common: Common = Common()
    ood: Ood = Ood()
    families: list[BFamily]

    @model_validator(mode="after")
    def _check(self) -> "BenchmarkFile":
        names = [f.name for f in self.families]
        if not names:
            raise ValueError("families: at least one")
        if len(set(names)) != len(names):
            raise ValueError(f"families: duplicate names in {names}")
        for i, f in enumerate(self.families):
            bad = set(f.shapes) - ALLOWED[f.behaviour]
            if bad:
                raise ValueError(f"families.{i}.shapes: {sorted(bad)} not drawn for behaviour {f.behaviour} "
                                 f"(allowed: {sorted(ALLOWED[f.behaviour])})")
            if not set(f.shapes) - set(self.ood.shapes):
                raise ValueError(f"families.{i}.shapes: every shape of {f.name} is held out in [ood]")
        c = self.common
        for name, full in (("angle_deg", c.angle_deg), ("width_m", c.width_m), ("actor_speed", c.actor_speed)):
            for r in getattr(self.ood, name):
                if r[0] < full[0] - 1e-9 or r[1] > full[1] + 1e-9:
                    raise ValueError(f"ood.{name}: band {list(r)} outside common.{name} {list(full)}")
        return self


def load_benchmark(name_or_path: str | Path) -> BenchmarkFile:
    """A roads suite file by name (common/data/suites/NAME.toml) or path.

    :raises ValueError: naming the file and the invalid field.
    """
    return load_toml(name_or_path, SUITES_DIR, BenchmarkFile, "suite")


# --------------------------------------------------------------------------------- drawing helpers
def _dir(a: float) -> np.ndarray:
    return np.array([math.cos(a), math.sin(a)])


def _right(d: np.ndarray) -> np.ndarray:
    return np.array([d[1], -d[0]])


def _complement(full: Range, bands: list[Range]) -> list[Range]:
    out, lo = [], full[0]
    for a, b in sorted(bands):
        if a > lo:
            out.append((lo, min(a, full[1])))
        lo = max(lo, b)
    if lo < full[1]:
        out.append((lo, full[1]))
    return [r for r in out if r[1] - r[0] > 1e-9]


def _uniform_in(rng, bands: list[Range]) -> float:
    w = np.array([b - a for a, b in bands])
    k = int(rng.choice(len(bands), p=w / w.sum())) if len(bands) > 1 else 0
    return float(rng.uniform(*bands[k]))


@dataclass
class Ctx:
    """One draw: the rng, the suite's ranges and which held-out band (if any) it draws from."""

    rng: np.random.Generator
    c: Common
    ood: Ood
    held: str | None = None
    used: set = field(default_factory=set)

    def u(self, r: Range) -> float:
        return float(self.rng.uniform(r[0], r[1]))

    def banded(self, dim: str, full: Range) -> float:
        """A draw of ``dim`` (angle_deg, width_m, actor_speed): from its held-out bands when this
        draw holds ``dim`` out, else from the range outside them."""
        bands = getattr(self.ood, dim)
        if self.held == dim:
            self.used.add(dim)
            return _uniform_in(self.rng, [(max(a, full[0]), min(b, full[1])) for a, b in bands])
        return _uniform_in(self.rng, _complement(full, bands))

    def speed(self) -> float:
        return self.banded("actor_speed", self.c.actor_speed)

    def speed_clamp(self) -> tuple[float, float]:
        full = self.c.actor_speed
        if self.held == "actor_speed":
            bands = self.ood.actor_speed
            return min(a for a, _ in bands), max(b for _, b in bands)
        parts = _complement(full, self.ood.actor_speed)
        return parts[0][0], parts[-1][1]

    def choice(self, seq):
        return seq[int(self.rng.integers(len(seq)))]


def _polyline_at(pts: np.ndarray, s: float) -> tuple[np.ndarray, int]:
    """Point at arc length s of a polyline and the index of the next vertex."""
    seg = np.hypot(*np.diff(pts, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    k = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
    u = (s - cum[k]) / max(seg[k], 1e-12)
    return pts[k] + (pts[k + 1] - pts[k]) * u, k + 1


def _hit_y(pts: np.ndarray, y: float) -> float | None:
    """Arc length of the first crossing of the polyline with the line y = const."""
    s = 0.0
    for a, b in zip(pts[:-1], pts[1:]):
        seg = float(np.hypot(*(b - a)))
        if (a[1] - y) * (b[1] - y) <= 0 and a[1] != b[1]:
            return s + seg * (y - a[1]) / (b[1] - a[1])
        s += seg
    return None


def _fillet(p_a, d_a, p_b, d_b, r: float, far: float = 12.0, n: int = 6) -> np.ndarray:
    """Polyline along line A (point, unit dir), a circular fillet of radius r, then along line B."""
    m = np.array([d_a, -d_b]).T
    if abs(np.linalg.det(m)) < 1e-9:  # parallel: straight on
        return np.array([p_a - far * d_a, p_a + far * d_a])
    s, _ = np.linalg.solve(m, p_b - p_a)
    x = p_a + s * d_a
    delta = math.atan2(d_a[0] * d_b[1] - d_a[1] * d_b[0], float(d_a @ d_b))
    t = r * math.tan(abs(delta) / 2)
    t1, t2 = x - t * d_a, x + t * d_b
    sg = 1.0 if delta > 0 else -1.0
    ctr = t1 + sg * r * np.array([-d_a[1], d_a[0]])
    a0 = math.atan2(*(t1 - ctr)[::-1])
    arc = [ctr + r * _dir(a0 + delta * k / n) for k in range(1, n)]
    return np.array([t1 - far * d_a, t1, *arc, t2, t2 + far * d_b])


# --------------------------------------------------------------------------------- maps
@dataclass
class Map:
    """A drawn map: its world fields and the actor lanes it offers."""

    shape: str
    width: float
    world: dict
    arms: list[np.ndarray]
    """Outward unit directions of the side roads at the junction (origin)."""
    bend_path: np.ndarray | None = None
    """bend: the incoming lane of the side road (travel direction), as a polyline."""
    angle: float | None = None


def draw_map(ctx: Ctx, shape: str) -> Map:
    c, rng = ctx.c, ctx.rng
    w = ctx.banded("width_m", c.width_m)
    roads = [{"cx": 0.0, "cy": 0.0, "yaw_deg": 0.0, "length": ROAD_LENGTH, "width": _r(w)}]
    ways: list[dict] = []
    arms: list[np.ndarray] = []
    bend = None
    ang = None
    side = 1.0 if rng.random() < 0.5 else -1.0
    if shape == "cross":
        ang = ctx.banded("angle_deg", c.angle_deg)
        roads.append({"cx": 0.0, "cy": 0.0, "yaw_deg": _r(ang), "length": 2 * SIDE_LENGTH, "width": _r(w)})
        a = math.radians(_r(ang))
        arms = [_dir(a), -_dir(a)]
    elif shape in ("t", "y"):
        if shape == "t":
            phi = ctx.u(c.t_angle_deg)
        else:
            ctx.used.add("shape")
            phi = ctx.u(c.y_angle_deg)
            if rng.random() < 0.5:
                phi = 180.0 - phi  # a backward branch
        a = side * phi
        ways.append({"x": 0.0, "y": 0.0, "yaw_deg": _r(a), "width": _r(w), "pieces": [{"straight": SIDE_LENGTH}]})
        arms = [_dir(math.radians(_r(a)))]
    elif shape == "bend":
        ang = ctx.banded("angle_deg", c.angle_deg)
        h_t = math.radians(ang) if side > 0 else math.radians(ang) - math.pi  # travel: +y (from the right) or -y
        target = math.pi / 2 if side > 0 else -math.pi / 2
        beta = math.radians(ctx.u(c.bend_deg))
        rad = ctx.u(c.bend_radius_m)
        sgn = 1.0 if h_t > target else -1.0  # turn that brings the road round from more perpendicular
        h0 = h_t - sgn * beta
        a_in = (w / 2) / abs(math.sin(h_t)) + 0.8
        p_in = -a_in * _dir(h_t)
        n = lambda h: np.array([-math.sin(h), math.cos(h)])  # noqa: E731
        ctr = p_in + sgn * rad * n(h_t)
        s_arc = ctr - sgn * rad * n(h0)
        s0 = s_arc - 3.0 * _dir(h0)
        pieces = [{"straight": 3.0}, {"arc_radius": _r(rad), "arc_deg": _r(math.degrees(sgn * beta))},
                  {"straight": _r(a_in + SIDE_LENGTH)}]
        ways.append({"x": _r(s0[0]), "y": _r(s0[1]), "yaw_deg": _r(math.degrees(h0)), "width": _r(w), "pieces": pieces})
        # the incoming lane, a quarter width right of the centre line: (left + 3 right) / 4 of the
        # curbs' vertices (the shared geometry; its arc every 15 deg, few waypoints)
        from racecav.common.world import Way, way_edges

        left, right = way_edges(Way.model_validate(ways[-1]), 15.0)
        bend = (np.asarray(left) + 3 * np.asarray(right)) / 4
        arms = [-_dir(h_t)]
    world = {"name": f"roads-{shape}", "kind": "roads", "lane_width": _r(w), "roads": roads}
    if ways:
        world["ways"] = ways
    return Map(shape=shape, width=w, world=world, arms=arms, bend_path=bend, angle=ang)


def _incoming(m: Map, arm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lane driving into the junction from ``arm``: (point, dir)."""
    d = -arm
    return (m.width / 4) * _right(d), d


def _outgoing(m: Map, arm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (m.width / 4) * _right(arm), arm


def _ego_lane(m: Map) -> tuple[np.ndarray, np.ndarray]:
    return np.array([0.0, -m.width / 4]), np.array([1.0, 0.0])


def _oncoming_lane(m: Map) -> tuple[np.ndarray, np.ndarray]:
    return np.array([0.0, m.width / 4]), np.array([-1.0, 0.0])


def _crossing_path(ctx: Ctx, m: Map, arms=None) -> np.ndarray:
    """A path that drives through the junction straight across the ego's road."""
    if m.bend_path is not None:
        return m.bend_path
    arm = ctx.choice(arms if arms is not None else m.arms)
    p, d = _incoming(m, arm)
    return np.array([p - 12 * d, p + 12 * d])


# --------------------------------------------------------------------------------- actors
@dataclass
class Actor:
    data: dict
    conflict: bool = True
    x: float = 0.0
    """Where it meets the ego's path, along the ego's road."""


@dataclass
class Draw:
    ego: dict
    actors: list[Actor]
    ego_distance: float
    """The ego's distance to where it must get past (progress = this + progress_past_m)."""
    duration: float


def _on_path(path: np.ndarray, s0: float) -> tuple[np.ndarray, list]:
    """Start point at arc length s0 of a path and the waypoints after it (at most 15)."""
    p, k = _polyline_at(path, s0)
    return p, [_pt(q) for q in path[k:][:15]]


def _actor(p, yaw: float, speed: float, path=(), start=None, sync=None, changes=()) -> dict:
    o = {"x": _r(p[0]), "y": _r(p[1]), "yaw_deg": _r(math.degrees(yaw)), "speed": _r(speed)}
    if len(path):
        o["path"] = [list(q) for q in path]
    if start:
        o["start"] = start
    if sync:
        o["sync"] = sync
    if changes:
        o["speed_changes"] = list(changes)
    return o


def _synced(ctx: Ctx, path: np.ndarray, s_cp: float, ego_pt, dist: float, v: float, changes=()) -> dict:
    """An actor ``dist`` before arc length ``s_cp`` of ``path``, started on the ego's time to
    arrival at ``ego_pt`` and synchronised to arrive at its point with the ego."""
    s0 = max(0.0, s_cp - dist)
    p, wps = _on_path(path, s0)
    cp, _ = _polyline_at(path, s_cp)
    nxt = np.asarray(wps[0]) if wps else p + _dir(0)
    yaw = math.atan2(nxt[1] - p[1], nxt[0] - p[0])
    lo, hi = ctx.speed_clamp()
    c = ctx.c
    start = {"kind": "time_to_arrival", "point": _pt(ego_pt), "value": _r((s_cp - s0) / v)}
    sync = {"ego_point": _pt(ego_pt), "actor_point": _pt(cp), "speed_min": _r(lo), "speed_max": _r(hi),
            "release_distance_m": _r(ctx.u(c.release_distance_m)), "release_time_s": _r(ctx.u(c.release_time_s))}
    if c.release_stopped_s is not None:
        sync["release_stopped_s"] = _r(c.release_stopped_s)
    return _actor(p, yaw, v, path=wps, start=start, sync=sync, changes=changes)


def _timed(path: np.ndarray, s0: float, v: float, start: dict | None = None, changes=()) -> dict:
    p, wps = _on_path(path, s0)
    nxt = np.asarray(wps[0]) if wps else p + _dir(0)
    yaw = math.atan2(nxt[1] - p[1], nxt[0] - p[0])
    return _actor(p, yaw, v, path=wps, start=start or {"kind": "time", "value": 0.0}, changes=changes)


def _parked(x: float, y: float, yaw: float = 0.0) -> dict:
    return _actor((x, y), yaw, 0.0)


def _cross_actor(ctx: Ctx, m: Map, y_e: float, brake: str | None = None, arms=None) -> Actor:
    """A synchronised actor crossing the ego's lane; ``brake``: "in" stops it in the ego's lane,
    "short" stops it short of the ego's path."""
    path = _crossing_path(ctx, m, arms)
    s_cp = _hit_y(path, y_e)
    cp, _ = _polyline_at(path, s_cp)
    v = ctx.speed()
    dist = ctx.u(ctx.c.actor_distance_m)
    chg = ()
    if brake:
        dec = ctx.u((2.0, 4.0))
        d = path[-1] - path[-2]
        sin = abs(d[1]) / math.hypot(*d)
        if brake == "in":
            stop = s_cp - ctx.u((0.0, 0.2))
        else:
            stop = s_cp - (CAR_L / 2 + (CAR_W / 2 + 0.2) / max(sin, 0.3) + ctx.u((0.3, 0.7)))
        at = max(0.0, stop - (s_cp - dist) - v * v / (2 * dec))
        chg = ({"at_m": _r(at), "speed": 0.0, "accel": _r(dec)},)
    return Actor(_synced(ctx, path, s_cp, (cp[0], y_e), dist, v, chg), conflict=brake != "short", x=cp[0])


def draw(ctx: Ctx, f: BFamily) -> tuple[Draw, Map]:
    c, rng = ctx.c, ctx.rng
    shapes = [s for s in f.shapes if s not in ctx.ood.shapes]
    if ctx.held == "shape":
        shapes = [s for s in f.shapes if s in ctx.ood.shapes]
    elif ctx.held == "angle_deg":
        shapes = [s for s in shapes if s in ("cross", "bend")]
    m = draw_map(ctx, ctx.choice(shapes))
    y_e = -m.width / 4 + ctx.u((-0.05, 0.05))
    de = ctx.u(c.ego_distance_m)
    v_e = ctx.u(c.ego_speed)
    acts: list[Actor] = []
    x_c = 0.0  # the furthest conflict point along the ego's road
    b = f.behaviour
    right_arms = [a for a in m.arms if a[1] < -1e-6]
    left_arms = [a for a in m.arms if a[1] > 1e-6]
    if b in ("crossing", "braking"):
        acts.append(_cross_actor(ctx, m, y_e, "in" if b == "braking" else None))
    elif b == "stop_short":
        acts.append(_cross_actor(ctx, m, y_e, "short"))
    elif b == "hidden":
        arm = ctx.choice(m.arms if m.width >= 2.4 else left_arms)
        acts.append(_cross_actor(ctx, m, y_e, arms=[arm]))
        sgn = 1.0 if arm[1] > 0 else -1.0  # parked on the curb of the side the actor comes from
        y_curb = sgn * (m.width / 2 - CAR_W / 2 - 0.05)
        # the side road's edge on that curb, then parked cars before it
        ang = math.radians(m.world["roads"][1]["yaw_deg"])
        x_edge = min((sgn * m.width / 2) / math.tan(ang) + k * (m.width / 2) / abs(math.sin(ang)) for k in (-1, 1))
        x = x_edge - CAR_L / 2 - ctx.u((0.05, 0.3))
        for _ in range(int(rng.integers(1, 3))):
            acts.append(Actor(_parked(x, y_curb), conflict=False))
            x -= CAR_L + ctx.u((0.1, 0.4))
        de = max(de, -x + 1.0)
    elif b in ("turn_across", "turn_away"):
        if b == "turn_across" or rng.random() < 0.5 or not left_arms:
            arms = right_arms if b == "turn_across" else left_arms
            if m.shape == "y":
                arms = [a for a in arms if a[0] < 0]
            if not arms:
                raise _Redraw
            p_a, d_a = _oncoming_lane(m)
            p_b, d_b = _outgoing(m, ctx.choice(arms))
        else:  # from a left side road, turning right into the oncoming lane
            p_a, d_a = _incoming(m, ctx.choice(left_arms))
            p_b, d_b = _oncoming_lane(m)
        path = _fillet(p_a, d_a, p_b, d_b, ctx.u(c.turn_radius_m))
        s_cp = _hit_y(path, y_e) if b == "turn_across" else None
        if b == "turn_across" and s_cp is None:
            raise _Redraw
        if s_cp is None:  # turn-away: timed to be in the junction when the ego arrives
            s_cp = float(np.hypot(*np.diff(path, axis=0).T)[:3].sum())
        cp, _ = _polyline_at(path, s_cp)
        ego_pt = (cp[0], y_e) if b == "turn_across" else (0.0, y_e)
        acts.append(Actor(_synced(ctx, path, s_cp, ego_pt, ctx.u(c.actor_distance_m), ctx.speed()), b == "turn_across",
                          x=ego_pt[0]))
    elif b == "merge":
        arms = [a for a in m.arms if not (m.shape == "y" and a[0] > 0)]
        if not arms:
            raise _Redraw
        p_a, d_a = _incoming(m, ctx.choice(arms))
        p_b, d_b = _ego_lane(m)
        path = _fillet(p_a, d_a, p_b + np.array([0.0, y_e + m.width / 4]), d_b, ctx.u(c.turn_radius_m))
        s_m = float(np.hypot(*np.diff(path, axis=0).T)[:-1].sum())  # end of the fillet: in the ego's lane
        cp, _ = _polyline_at(path, s_m)
        gap = ctx.u((0.3, 0.6))
        dist = ctx.u(c.actor_distance_m)
        slow = ({"at_m": _r(dist), "speed": _r(ctx.u((0.0, 0.2))), "accel": _r(ctx.u((1.0, 3.0)))},)
        acts.append(Actor(_synced(ctx, path, s_m, (cp[0] - gap, y_e), dist, ctx.speed(), slow)))
        x_c = max(x_c, cp[0])
    elif b == "cut_in":
        lc = ctx.u((1.0, 2.0))
        y_l = m.width / 4
        path = np.array([[-20.0, y_l], [-lc, y_l], [0.0, y_e], [20.0, y_e]])
        gap = ctx.u((0.6, 0.9))
        v = ctx.speed()
        dist = ctx.u(c.actor_distance_m)
        s_m = 20.0 - lc + math.hypot(lc, y_l - y_e)
        slow = ({"at_m": _r(dist), "speed": _r(ctx.u((0.0, 0.2))), "accel": _r(ctx.u((2.0, 4.0)))},)
        acts.append(Actor(_synced(ctx, path, s_m, (-gap, y_e), dist, v, slow)))
    elif b == "head_on":
        dist = ctx.u(c.actor_distance_m)
        s0 = np.array([dist, m.width / 4 + ctx.u((-0.1, 0.1))])
        p = np.array([0.0, y_e])
        d = (p - s0) / np.hypot(*(p - s0))
        path = np.array([s0, s0 + 20 * d])
        acts.append(Actor(_synced(ctx, path, dist_to(s0, p), tuple(p), dist_to(s0, p), ctx.speed())))
    elif b == "multi":
        n = int(rng.integers(2, 4))
        acts.append(_cross_actor(ctx, m, y_e, arms=[m.arms[0]]))
        acts.append(_cross_actor(ctx, m, y_e, arms=[m.arms[1]]))
        if n == 3:
            p_a, d_a = _oncoming_lane(m)
            p_b, d_b = _outgoing(m, ctx.choice(right_arms))
            path = _fillet(p_a, d_a, p_b, d_b, ctx.u(c.turn_radius_m))
            s_cp = _hit_y(path, y_e)
            if s_cp is None:
                raise _Redraw
            cp, _ = _polyline_at(path, s_cp)
            acts.append(Actor(_synced(ctx, path, s_cp, (cp[0], y_e), ctx.u(c.actor_distance_m), ctx.speed()), x=cp[0]))
    elif b in ("rear_stationary", "rear_slow", "rear_braking"):
        p = ctx.u(c.overlap) if b == "rear_stationary" else 1.0
        y_t = y_e + (1.0 if p >= 0 else -1.0) * (1.0 - abs(p)) * CAR_W
        if b == "rear_stationary":
            gap = ctx.u(c.ttc_s) * v_e
            acts.append(Actor(_parked(0.0, y_t)))
            de = gap + CAR_L
        elif b == "rear_slow":
            v_l = ctx.u((0.2, min(0.6, v_e - 0.3)))
            gap = ctx.u(c.ttc_s) * (v_e - v_l)
            acts.append(Actor(_actor((0.0, y_t), 0.0, v_l, start={"kind": "time", "value": 0.0})))
            de = gap + CAR_L
        else:
            h = ctx.u(c.headway_m)
            dec = ctx.u(c.lead_decel)
            at = v_e * ctx.u((0.3, 1.2))
            acts.append(Actor(_actor((0.0, y_t), 0.0, v_e, start={"kind": "time", "value": 0.0},
                                     changes=({"at_m": _r(at), "speed": 0.0, "accel": _r(dec)},))))
            de = h + CAR_L + at + v_e * v_e / (2 * dec)
    elif b in ("pass_ahead", "pass_behind"):
        path = _crossing_path(ctx, m)
        s_cp = _hit_y(path, y_e)
        cp, _ = _polyline_at(path, s_cp)
        if b == "pass_ahead":
            de = ctx.u((5.0, 6.5))
            acts.append(Actor(_timed(path, s_cp - ctx.u((0.3, 1.0)), ctx.banded("actor_speed", (1.5, c.actor_speed[1]))), False))
        else:
            x_c = cp[0] + ctx.u((1.2, 1.8))
            start = {"kind": "distance", "point": _pt((x_c, y_e)), "value": 0.3}
            acts.append(Actor(_timed(path, s_cp - ctx.u((1.2, 2.5)), ctx.speed(), start=start), False))
    elif b == "oncoming":
        dist = ctx.u((4.0, 9.0))
        y_o = m.width / 4 + ctx.u((-0.05, 0.05))
        acts.append(Actor(_actor((dist, y_o), math.pi, ctx.speed(), start={"kind": "time", "value": 0.0}), False))
    elif b == "parked":
        sides = [1.0, -1.0] if m.width >= 2.4 else [1.0]
        sgn = ctx.choice(sides)
        x = ctx.u((-2.0, 3.0))
        if m.shape != "straight" and abs(x) < m.width:
            x = -m.width - ctx.u((0.0, 1.0))
        acts.append(Actor(_parked(x, sgn * (m.width / 2 - CAR_W / 2 - 0.05), math.pi * (rng.random() < 0.5)), False))
    elif b == "from_rest":
        de = ctx.u(c.rest_distance_m)
        v_e = 0.0
        if m.shape != "straight" and rng.random() < 0.5:  # a car has just gone by
            path = _crossing_path(ctx, m) if m.shape in ("cross", "bend") else None
            if path is not None:
                s_cp = _hit_y(path, y_e)
                acts.append(Actor(_timed(path, s_cp + ctx.u((0.6, 1.2)), ctx.speed()), False))
    x_c = max([x_c] + [a.x for a in acts])
    need = de + max(0.0, x_c)  # past the furthest conflict point
    dur = need / 0.6 + c.margin_s + (2.0 if v_e == 0 else 0.0)
    ego = {"x": _r(-de), "y": _r(y_e), "yaw_deg": 0.0, "speed": _r(v_e)}
    return Draw(ego=ego, actors=acts, ego_distance=need, duration=dur), m


def dist_to(a, b) -> float:
    return float(np.hypot(*(np.asarray(b) - np.asarray(a))))


class _Redraw(Exception):
    """This draw cannot be built (e.g. no side road on the needed side): draw again."""


def scenario_data(d: Draw, m: Map, f: BFamily, c: Common, name: str, drop_conflicts: bool = False) -> dict:
    kind = "control: a non-evading car passes" if f.control else "conflict: a non-evading car collides"
    return {
        "name": name,
        "description": f"roads benchmark, family {f.name} ({f.behaviour}) on a {m.shape} map; {kind}",
        "duration_s": _r(d.duration),
        "ego": d.ego,
        "obstacles": [a.data for a in d.actors if not (drop_conflicts and a.conflict)],
        "randomize": {"ego_xy": 0.05, "ego_yaw_deg": 0.5, "ego_speed": 0.05, "obstacle_xy": 0.05,
                      "obstacle_yaw_deg": 1.0},
        "success": {"min_progress_m": _r(d.ego_distance + c.progress_past_m)},
        "map": m.world,
    }


# --------------------------------------------------------------------------------- validation
def reference_outcomes(scenarios: list[Scenario], trials: int = CHECK_TRIALS, seed: int = 0,
                       shifts=VALIDATION_SHIFTS, until_end: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Both non-evading references (straight at 1 m/s and at full throttle) on the fast world,
    ``trials`` randomised trials each, with the ego's start shifted by each of ``shifts``.
    A trial ends at its contact, at the scenario's duration, or once the ego is
    ``PASSED_M`` past its required progress without contact (its straight path meets nothing
    more: it has passed); ``until_end``: every trial runs its whole duration, as an evaluation.

    :return: (collided, succeeded), bool (len(scenarios), 2 references, shifts x trials).
    """
    from racecav.common.vehicle import load_car, throttle_for_speed
    from racecav.sim.fast_world import FastWorld

    car = load_car()
    thr = [1.0 if v is None else float(throttle_for_speed(v, car, car.agent_speed_scale)) for v in REFERENCE_SPEEDS]
    n_s, n_r = len(shifts), len(REFERENCE_SPEEDS)
    col = np.zeros((len(scenarios), n_r, n_s * trials), bool)
    ok = np.zeros_like(col)
    by_world: dict[str, list[int]] = {}
    for i, sc in enumerate(scenarios):
        by_world.setdefault(sc.world_key, []).append(i)
    for idx in by_world.values():
        scs = [scenarios[i].ego_shifted(dy) for i in idx for dy in shifts]
        per = n_r * trials  # envs per (scenario, shift)
        fw = FastWorld(n_envs=len(scs) * per, scenarios=scs, car=car, seed=seed)
        fw.scenario_of_env = np.repeat(np.arange(len(scs)), per)
        fw.reset()
        a = np.zeros((fw.n_envs, 2))
        a[:, 0] = np.tile(np.repeat(thr, trials), len(scs))
        c = np.zeros(fw.n_envs, bool)
        live = np.ones(fw.n_envs, bool)
        passed = np.zeros(fw.n_envs, bool)
        while live.any():
            _, _, hit, _ = fw.step(a, observe=False)
            c |= hit & live
            if not until_end:
                passed |= live & ~c & (fw.progress() >= fw.min_progress + PASSED_M)
            live &= (fw.time < fw.time_limit - 1e-9) & ~c & ~passed
        good = (passed | fw.success()) & ~c
        # env order: scenario, shift, reference, trial
        shape = (len(idx), n_s, n_r, trials)
        col[idx] = c.reshape(shape).transpose(0, 2, 1, 3).reshape(len(idx), n_r, n_s * trials)
        ok[idx] = good.reshape(shape).transpose(0, 2, 1, 3).reshape(len(idx), n_r, n_s * trials)
    return col, ok


def valid(d: Draw, m: Map, f: BFamily, c: Common, seed: int) -> bool:
    """The generation check of one draw (see the module docstring)."""
    sc = Scenario.model_validate(scenario_data(d, m, f, c, "check"))
    if f.control:  # to the end: a car may still come after the ego has passed its point
        _, ok = reference_outcomes([sc], seed=seed, until_end=True)
        return bool(ok.all())
    free = Scenario.model_validate(scenario_data(d, m, f, c, "check", drop_conflicts=True))
    col, ok = reference_outcomes([sc, free], seed=seed)  # one world: one run
    return bool(col[0].all() and ok[1].all())


# --------------------------------------------------------------------------------- generation
def _held_dims(bf: BenchmarkFile, f: BFamily) -> list[str]:
    """The held-out bands a file of family ``f`` can draw from."""
    o = bf.ood
    dims = []
    if set(f.shapes) & set(o.shapes):
        dims.append("shape")
    if o.angle_deg and set(f.shapes) & {"cross", "bend"} - set(o.shapes):
        dims.append("angle_deg")
    if o.width_m:
        dims.append("width_m")
    if o.actor_speed and f.behaviour not in ("rear_stationary", "rear_slow", "rear_braking", "parked", "from_rest"):
        dims.append("actor_speed")
    return dims


def _split_plan(bf: BenchmarkFile) -> list[tuple[str, BFamily, int]]:
    out = []
    for split in SPLITS:
        for f in bf.families:
            if split == "train":
                out.append((split, f, bf.n_train))
            elif split in ("test", "ood") and not f.control:
                out.append((split, f, bf.n_test))
            elif split == "controls" and f.control:
                out.append((split, f, bf.n_test))
    return out


def generate(bf: BenchmarkFile, out: Path, seed: int = 0, splits=SPLITS, progress: bool = True,
             n_test: int | None = None, n_train: int | None = None) -> dict:
    """Draw, validate and write the splits; returns the manifest (also suite.json)."""
    import tomli_w
    from tqdm import tqdm

    n_test = n_test or bf.n_test
    n_train = n_train or bf.n_train
    out.mkdir(parents=True, exist_ok=True)
    man_path = out / "suite.json"
    old = json.loads(man_path.read_text()) if man_path.is_file() else {}
    manifest = {"name": bf.name, "generator": "roads",
                "families": [f.name for f in bf.families if not f.control],
                "controls": [f.name for f in bf.families if f.control],
                "seed": seed, "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "ood": bf.ood.model_dump(), "splits": {}, "redrawn": {}}
    if old.get("name") == bf.name and old.get("seed") == seed:  # keep the splits not regenerated
        for s in SPLITS:
            if s not in splits and s in old.get("splits", {}):
                manifest["splits"][s] = old["splits"][s]
                manifest["redrawn"][s] = old.get("redrawn", {}).get(s, {})
    plan = [(s, f, n_train if s == "train" else n_test) for s, f, _ in _split_plan(bf) if s in splits]
    bar = tqdm(total=sum(n for *_, n in plan), desc=f"suite {bf.name}", unit="file", disable=not progress)
    for split in splits:
        (out / split).mkdir(exist_ok=True)
        for f in (out / split).glob("*.toml"):
            f.unlink()
        manifest["splits"][split] = []
        manifest["redrawn"][split] = {}
    si_of = {s: i for i, s in enumerate(SPLITS)}
    for split, fam, n in plan:
        si, fi = si_of[split], [f.name for f in bf.families].index(fam.name)
        redrawn = 0
        dims = _held_dims(bf, fam)
        for i in range(n):
            for attempt in range(MAX_ATTEMPTS):
                sd = [seed, si, fi, i, attempt]
                rng = np.random.default_rng(sd)
                held = None
                if split == "ood":
                    if not dims:
                        raise ValueError(f"families: {fam.name} has no parameter [ood] holds out")
                    held = dims[int(rng.integers(len(dims)))]
                ctx = Ctx(rng, bf.common, bf.ood, held)
                try:
                    d, m = draw(ctx, fam)
                except _Redraw:
                    redrawn += 1
                    continue
                if held and held not in ctx.used:
                    redrawn += 1
                    continue
                if valid(d, m, fam, bf.common, seed=seed + 7919 * si):
                    break
                redrawn += 1
            else:
                raise RuntimeError(f"family {fam.name}: no valid draw in {MAX_ATTEMPTS} attempts")
            name = f"{fam.name}-{i:04d}"
            data = scenario_data(d, m, fam, bf.common, name)
            path = out / split / f"{name}.toml"
            path.write_text(f"# generated by `racecav suite generate --name {bf.name}` (family {fam.name}, "
                            f"split {split}, shape {m.shape}, seed {sd})\n" + tomli_w.dumps(data))
            manifest["splits"][split].append({"file": f"{split}/{path.name}", "family": fam.name, "shape": m.shape,
                                              "control": fam.control, "ood": split == "ood", "held_out": held,
                                              "seed": sd})
            bar.update(1)
        manifest["redrawn"][split][fam.name] = redrawn
    bar.close()
    for s in manifest["splits"]:
        manifest["splits"][s] = sorted(manifest["splits"][s], key=lambda e: e["file"])
    man_path.write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


# --------------------------------------------------------------------------------- figure
def plot_families(bf: BenchmarkFile, path: Path, seed: int = 0) -> Path:
    """One validated draw of every family (the train bands): walls, the ego (green) and each
    actor's start and path (red; parked cars black, x: synchronised conflict points)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from racecav.common.world import plot_world

    cols = 6
    rows = math.ceil(len(bf.families) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.3 * cols, 2.6 * rows))
    for k, (ax, fam) in enumerate(zip(np.ravel(axes), bf.families)):
        for attempt in range(MAX_ATTEMPTS):
            ctx = Ctx(np.random.default_rng([seed, 9, k, attempt]), bf.common, bf.ood)
            try:
                d, m = draw(ctx, fam)
            except _Redraw:
                continue
            if valid(d, m, fam, bf.common, seed):
                break
        sc = Scenario.model_validate(scenario_data(d, m, fam, bf.common, fam.name))
        plot_world(sc.build_world(), ax, show_centerline=False)
        e = sc.ego
        ax.annotate("", xy=(e.x + 1.0, e.y), xytext=(e.x, e.y), arrowprops=dict(arrowstyle="->", color="g", lw=2))
        for o in sc.obstacles:
            pts = np.vstack([[o.x, o.y], np.asarray(o.path, float).reshape(-1, 2)])
            if len(pts) == 1:
                pts = np.vstack([pts, pts[0] + 3.0 * _dir(math.radians(o.yaw_deg))])
            if o.speed > 0:
                ax.plot(pts[:, 0], pts[:, 1], "r-", lw=0.8)
            ax.plot(o.x, o.y, "s", color="r" if o.speed > 0 else "k", ms=4)
            if o.sync is not None:
                ax.plot(*o.sync.actor_point, "rx", ms=4)
        ax.set_xlim(-7.5, 5.5)
        ax.set_ylim(-4.5, 4.5)
        ax.set_xlabel("")
        ax.set_ylabel("")
        ax.set_title(f"{fam.name}{' (control)' if fam.control else ''}: {m.shape}", fontsize=9)
    for ax in np.ravel(axes)[len(bf.families):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    """``python -m racecav.evaluation.benchmark OUT.png [SUITE]``: the docs/world.md figure."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    if not args:
        print("usage: python -m racecav.evaluation.benchmark OUT.png [SUITE]")
        return 2
    plot_families(load_benchmark(args[1] if len(args) > 1 else "roads"), Path(args[0]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
