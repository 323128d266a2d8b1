"""``racecav suite generate``: the procedural conflict suite, scenario files drawn from families.

    racecav suite generate [--name conflicts] [--families FILE] [--n 140] [--n-train 1400]
                           [--seed 0] [--out DIR]
    racecav suite list [NAME|DIR]

A family file (common/data/suites/NAME.toml, fields in docs/world.md) declares families of
conflicts (crossing from either side at 45-135 deg, head-on with an offset, turning across or
into the ego's road, braking to a stop in the ego's lane, a stopped car, two staggered actors)
as ranges. Each generated file is one scenario (common/scenario.py) whose actors are timed by the
ego (start trigger on its time to arrival + synchronised arrival, sim/actors.py). Every file
is validated at generation on the fast world: a non-evading ego driving straight at 1 m/s and at
full throttle must collide in every check trial (randomised as in the file, and with the ego's
start shifted 5 cm to either side: a margin against near misses), else the file is redrawn
(counted).

A family may instead be timed by the clock (``timing = "clock"``: the actor starts after a drawn
delay and keeps its speed): traffic that may or may not conflict, for a training mix that
teaches reading the other car's motion rather than always evading. A family file of such
families sets ``validate = false``; it is never a benchmark (common/data/suites/traffic.toml).

Output: ``runs/suites/NAME/{train,test}/FAMILY-NNNN.toml`` and ``suite.json`` (family, seed and
file of every scenario, the redraw counts). The two splits come from disjoint seeds
(``[seed, split, family, index, attempt]``), so training never sees a test file.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from racecav.common.scenario import Scenario
from racecav.common.vehicle import load_toml

log = logging.getLogger("racecav.suite")

SUITES_DIR = Path(__file__).resolve().parent.parent / "common" / "data" / "suites"
SPLITS = ("train", "test")
REFERENCE_SPEEDS = (1.0, None)
"""Validation egos: straight at 1 m/s and at full throttle (None)."""
CHECK_TRIALS = 4
"""Randomised trials per reference ego in the validation (all must collide)."""
VALIDATION_SHIFTS = (0.0, -0.05, 0.05)
"""m: the validation egos also start this far to either side (near misses are redrawn)."""
MAX_ATTEMPTS = 200
LANE_OFFSET = 0.6
"""m: the centre of a lane of the 2.4 m roads (right-hand traffic)."""

Range = tuple[float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _check_ranges(model: BaseModel) -> None:
    for name, val in model:
        if isinstance(val, tuple) and len(val) == 2 and all(isinstance(v, (int, float)) for v in val):
            if val[0] > val[1]:
                raise ValueError(f"{name}: low {val[0]} > high {val[1]}")


class Common(_Strict):
    ego_distance_m: Range = (4.5, 6.5)
    ego_lateral_m: Range = (-0.4, 0.4)
    ego_speed: Range = (0.8, 1.4)
    obstacle_speed: Range = (0.5, 2.0)
    obstacle_distance_m: Range = (3.0, 5.0)
    sync_speed: Range = (0.5, 2.0)
    release_time_s: Range = (0.6, 1.0)
    release_distance_m: Range = (0.8, 1.2)
    margin_s: float = Field(3.0, ge=0)
    progress_past_m: float = Field(1.5, ge=0)
    start_s: Range = (0.0, 4.0)     # clock-timed families: the actor starts after this delay
    duration_s: Range | None = None
    """Episode length, drawn; default: the time a 0.6 m/s ego needs to its point + margin_s (a free
    road needs no slow-ego margin: its episode ends once the ego is through the crossing)."""

    @model_validator(mode="after")
    def _ranges(self) -> "Common":
        _check_ranges(self)
        if self.sync_speed[0] <= 0 or self.ego_distance_m[0] <= 0 or self.obstacle_distance_m[0] <= 0:
            raise ValueError("sync_speed, ego_distance_m, obstacle_distance_m: must be positive")
        if self.duration_s is not None and self.duration_s[0] <= 0:
            raise ValueError("duration_s: must be positive")
        return self


class Family(_Strict):
    name: str = Field(pattern=r"^[a-z0-9][a-z0-9-]*$")
    kind: Literal["crossing", "head_on", "turning", "braking", "stopped", "staggered", "empty"]
    """empty: no other car, the road is free (for training mixes: what a policy does when nothing
    is there to avoid)."""
    world: str
    weight: float = Field(1.0, gt=0)
    timing: Literal["ego", "clock", "paper"] = "ego"
    """ego: started and synchronised by the ego (a conflict at any ego speed); clock: starts
    after ``common.start_s`` at its constant speed (may or may not conflict); paper: the paper's
    Table 1 timing, constant speed, reaching the conflict point when an ego holding its start
    speed does, ``common.start_s`` later (a faster or evading ego may pass; crossing and
    head-on kinds only)."""
    side: Literal["right", "left", "either"] = "either"
    angle_deg: Range = (45.0, 135.0)
    lateral_offset_m: Range = (-0.5, 0.5)
    variants: list[Literal["left_across", "right_into"]] = ["left_across", "right_into"]
    stop_distance_m: Range = (0.0, 0.4)
    brake_decel: Range = (2.0, 4.0)
    yaw_deg: Range = (-30.0, 30.0)
    gap_m: Range = (1.0, 2.0)

    @model_validator(mode="after")
    def _ranges(self) -> "Family":
        _check_ranges(self)
        if not 0 < self.angle_deg[0] <= self.angle_deg[1] < 180:
            raise ValueError("angle_deg: within (0, 180)")
        if self.brake_decel[0] <= 0:
            raise ValueError("brake_decel: must be positive")
        if not self.variants:
            raise ValueError("variants: at least one")
        if self.timing == "paper" and self.kind not in ("crossing", "head_on"):
            raise ValueError(f"timing = \"paper\": crossing or head_on kinds only, not {self.kind!r}")
        return self


class FamilyFile(_Strict):
    name: str
    description: str = ""
    common: Common = Common()
    families: list[Family]
    validate_conflicts: bool = Field(True, alias="validate")
    """Every file must collide with a non-evading ego (a benchmark); false for traffic mixes."""

    @model_validator(mode="after")
    def _unique(self) -> "FamilyFile":
        names = [f.name for f in self.families]
        if not names:
            raise ValueError("families: at least one")
        if len(set(names)) != len(names):
            raise ValueError(f"families: duplicate names in {names}")
        empty = [f.name for f in self.families if f.kind == "empty"]
        if empty and self.validate_conflicts:
            raise ValueError(f"families {', '.join(empty)}: kind \"empty\" has no conflict; "
                             "set validate = false (a training mix, not a benchmark)")
        return self


def load_families(name_or_path: str | Path) -> FamilyFile:
    """A family file by name (common/data/suites/NAME.toml) or path.

    :raises ValueError: naming the file and the invalid field.
    """
    return load_toml(name_or_path, SUITES_DIR, FamilyFile, "family")


# --------------------------------------------------------------------------------- drawing
def _u(rng: np.random.Generator, r: Range) -> float:
    return float(rng.uniform(r[0], r[1]))


def _r(v: float) -> float:
    return round(float(v), 4)


def _pt(p) -> list[float]:
    return [_r(p[0]), _r(p[1])]


def _arc(cx: float, cy: float, rad: float, a0: float, a1: float, n: int = 6) -> list[list[float]]:
    """Points (after the first) of an arc around (cx, cy) from angle a0 to a1 (rad)."""
    return [[cx + rad * math.cos(a), cy + rad * math.sin(a)] for a in np.linspace(a0, a1, n + 1)[1:]]


def _crossing_point(start, path, y: float):
    """First point where the polyline start -> path crosses the line y = const, with its arc length."""
    pts = np.vstack([start, np.asarray(path, float).reshape(-1, 2)])
    s = 0.0
    for a, b in zip(pts[:-1], pts[1:]):
        seg = float(np.hypot(*(b - a)))
        if (a[1] - y) * (b[1] - y) <= 0 and a[1] != b[1]:
            u = (y - a[1]) / (b[1] - a[1])
            return a + (b - a) * u, s + seg * u
        s += seg
    return None, None


@dataclass
class Draw:
    """A family member being built: the ego and its actors (scenario file fields)."""

    ego: dict
    obstacles: list[dict]
    ego_distance: float
    duration: float | None = None


def _actor(x, y, yaw, speed, path=(), start=None, sync=None, changes=()) -> dict:
    o = {"x": _r(x), "y": _r(y), "yaw_deg": _r(math.degrees(yaw)), "speed": _r(speed)}
    if path:
        o["path"] = [_pt(p) for p in path]
    if start:
        o["start"] = start
    if sync:
        o["sync"] = sync
    if changes:
        o["speed_changes"] = list(changes)
    return o


def _timing(rng, c: Common, f: Family, ego_pt, actor_pt, dist: float, v_nom: float) -> tuple[dict, dict | None]:
    """Start trigger (the ego's time to arrival at its point = the actor's nominal time to its
    point) and synchronised arrival of one actor; for a clock- or paper-timed family a start
    delay only."""
    if f.timing in ("clock", "paper"):
        return {"kind": "time", "value": _r(_u(rng, c.start_s))}, None
    start = {"kind": "time_to_arrival", "point": _pt(ego_pt), "value": _r(dist / v_nom)}
    sync = {"ego_point": _pt(ego_pt), "actor_point": _pt(actor_pt),
            "speed_min": _r(c.sync_speed[0]), "speed_max": _r(c.sync_speed[1]),
            "release_distance_m": _r(_u(rng, c.release_distance_m)),
            "release_time_s": _r(_u(rng, c.release_time_s))}
    return start, sync


def _paper_speed(f: Family, dist: float, v: float, t_meet: float) -> float:
    """The actor's speed under the paper's timing: it covers ``dist`` in the time an ego holding
    its start speed needs to its point (``t_meet``), so its start delay makes it that much late
    (the paper's 0-0.3 s); other timings keep ``v``."""
    return dist / t_meet if f.timing == "paper" else v


def _crossing_actor(rng, c: Common, f: Family, p, side: str, angle_deg: float, changes=False,
                    t_meet: float = 0.0) -> dict:
    th = math.radians(angle_deg)
    d = np.array([math.cos(th), math.sin(th) if side == "right" else -math.sin(th)])
    dist = _u(rng, c.obstacle_distance_m)
    v = _u(rng, c.obstacle_speed)
    s0 = np.asarray(p) - dist * d
    start, sync = _timing(rng, c, f, p, p, dist, v)
    v = _paper_speed(f, dist, v, t_meet)
    chg = ()
    if changes:  # brake to a stop with the centre stop_distance before the ego's path
        dec = _u(rng, f.brake_decel)
        stop = _u(rng, f.stop_distance_m) / max(math.sin(th), 0.3)
        at = max(0.0, dist - stop - v * v / (2 * dec))
        chg = ({"at_m": _r(at), "speed": 0.0, "accel": _r(dec)},)
    return _actor(s0[0], s0[1], math.atan2(d[1], d[0]), v, start=start, sync=sync, changes=chg)


def draw(rng: np.random.Generator, c: Common, f: Family) -> Draw:
    """One scenario of family ``f`` (the ego drives along +x towards its conflict point at x = 0)."""
    de = _u(rng, c.ego_distance_m)
    y0 = _u(rng, c.ego_lateral_m)
    ego = {"x": _r(-de), "y": _r(y0), "yaw_deg": 0.0, "speed": _r(_u(rng, c.ego_speed))}
    p = (0.0, y0)
    side = f.side if f.side != "either" else ("right" if rng.random() < 0.5 else "left")
    obs: list[dict] = []
    t_meet = de / ego["speed"]  # the paper's timing: when an ego holding its start speed arrives
    if f.kind == "crossing":
        obs.append(_crossing_actor(rng, c, f, p, side, _u(rng, f.angle_deg), t_meet=t_meet))
    elif f.kind == "braking":
        obs.append(_crossing_actor(rng, c, f, p, side, _u(rng, f.angle_deg), changes=True))
    elif f.kind == "head_on":
        dist = _u(rng, c.obstacle_distance_m)
        off = _u(rng, f.lateral_offset_m)
        s0 = np.array([dist, y0 + off])
        d = (np.asarray(p) - s0) / np.hypot(*(np.asarray(p) - s0))
        v = _u(rng, c.obstacle_speed)
        path_len = float(np.hypot(*(np.asarray(p) - s0)))
        start, sync = _timing(rng, c, f, p, p, path_len, v)
        v = _paper_speed(f, path_len, v, t_meet)
        obs.append(_actor(s0[0], s0[1], math.atan2(d[1], d[0]), v, start=start, sync=sync))
    elif f.kind == "turning":
        variant = f.variants[int(rng.integers(len(f.variants)))]
        rad = float(rng.uniform(0.7, 1.1))
        if variant == "left_across":  # oncoming in the other lane, turns left across the ego's path
            xt = float(rng.uniform(0.2, 0.8))
            lead = _u(rng, c.obstacle_distance_m)
            start = np.array([xt + lead, LANE_OFFSET])
            path = [[xt, LANE_OFFSET]] + _arc(xt, LANE_OFFSET - rad, rad, math.pi / 2, math.pi)
            path.append([xt - rad, -8.0])
            yaw = math.pi
        else:  # from the crossing road on the right, turns right into the ego's lane ahead of it
            yt = y0 - rad
            lead = _u(rng, c.obstacle_distance_m)
            start = np.array([LANE_OFFSET, yt - lead])
            path = [[LANE_OFFSET, yt]] + _arc(LANE_OFFSET + rad, yt, rad, math.pi, math.pi / 2)
            path.append([12.0, y0])
            yaw = math.pi / 2
        cp, s_c = _crossing_point(start, path, y0 - 1e-6 if variant == "right_into" else y0)
        if cp is None:
            raise ValueError("turning: the path does not cross the ego's path")
        ego_pt = (float(cp[0]), y0)
        v = _u(rng, c.obstacle_speed)
        st, sync = _timing(rng, c, f, ego_pt, cp, s_c, v)
        obs.append(_actor(start[0], start[1], yaw, v, path=path, start=st, sync=sync))
        de = de + ego_pt[0]  # the ego's distance to its conflict point
    elif f.kind == "stopped":
        yaw = math.radians(_u(rng, f.yaw_deg)) + (math.pi if rng.random() < 0.5 else 0.0)
        obs.append(_actor(0.0, y0 + _u(rng, f.lateral_offset_m), yaw, 0.0))
    elif f.kind == "staggered":
        gap = _u(rng, f.gap_m)
        p1, p2 = (-gap / 2, y0), (gap / 2, y0)
        obs.append(_crossing_actor(rng, c, f, p1, "right", 90.0))
        obs.append(_crossing_actor(rng, c, f, p2, "left", 90.0))
        de = de - gap / 2
    # "empty": no actor; the ego's start is drawn as for the others
    return Draw(ego=ego, obstacles=obs, ego_distance=de,
                duration=None if c.duration_s is None else _u(rng, c.duration_s))


def _description(f: Family) -> str:
    if f.kind == "empty":
        return f"free road, family {f.name}: no other car"
    if f.timing == "ego":
        return (f"conflict suite, family {f.name} ({f.kind}): timed by the ego; "
                "a non-evading ego collides at 1 m/s and at full throttle")
    if f.timing == "paper":
        return (f"traffic, family {f.name} ({f.kind}): timed like the paper's Table 1 (meets an ego "
                "holding its start speed); a faster or evading ego may pass")
    return f"traffic, family {f.name} ({f.kind}): timed by the clock; may or may not conflict"


def scenario_data(d: Draw, c: Common, f: Family, name: str) -> dict:
    """The scenario file's fields."""
    return {
        "name": name,
        "description": _description(f),
        "world": f.world,
        "duration_s": _r(d.ego_distance / 0.6 + c.margin_s if c.duration_s is None else d.duration),
        "ego": d.ego,
        "obstacles": d.obstacles,
        "randomize": {"ego_xy": 0.05, "ego_yaw_deg": 0.5, "ego_speed": 0.05, "obstacle_xy": 0.05,
                      "obstacle_yaw_deg": 1.0},
        "success": {"min_progress_m": _r(d.ego_distance + c.progress_past_m)},
    }


# --------------------------------------------------------------------------------- validation
def straight_collisions(scenarios: list[Scenario], speeds=REFERENCE_SPEEDS, trials: int = CHECK_TRIALS,
                        seed: int = 0) -> np.ndarray:
    """Non-evading egos on the fast world: does a car driving straight at each reference speed
    (m/s; None = full throttle) collide in every one of ``trials`` randomised trials?

    :return: bool (len(scenarios), len(speeds)): True where every trial collided.
    """
    from racecav.common.vehicle import load_car, throttle_for_speed
    from racecav.sim.fast_world import FastWorld

    car = load_car()
    out = np.zeros((len(scenarios), len(speeds)), bool)
    by_world: dict[str, list[int]] = {}
    for i, sc in enumerate(scenarios):
        by_world.setdefault(sc.world_key, []).append(i)
    for idx in by_world.values():
        scs = [scenarios[i] for i in idx]
        n = len(scs) * trials
        for j, v in enumerate(speeds):
            thr = 1.0 if v is None else float(throttle_for_speed(v, car, car.agent_speed_scale))
            fw = FastWorld(n_envs=n, scenarios=scs, car=car, seed=seed)
            fw.scenario_of_env = np.repeat(np.arange(len(scs)), trials)
            fw.reset()
            col = np.zeros(n, bool)
            live = np.ones(n, bool)
            a = np.tile([thr, 0.0], (n, 1))
            while live.any():
                _, _, c, _ = fw.step(a)
                col |= c & live
                live &= fw.time < fw.time_limit - 1e-9
            out[idx, j] = col.reshape(len(scs), trials).all(axis=1)
    return out


# --------------------------------------------------------------------------------- generation
def _counts(ff: FamilyFile, n: int) -> dict[str, int]:
    """Files per family for n files in all (by weight, at least one each)."""
    w = np.array([f.weight for f in ff.families])
    k = np.maximum(1, np.floor(n * w / w.sum()).astype(int))
    i = 0
    while k.sum() < n:
        k[i % len(k)] += 1
        i += 1
    return {f.name: int(c) for f, c in zip(ff.families, k)}


def generate(ff: FamilyFile, out: Path, n_test: int, n_train: int, seed: int = 0,
             progress: bool = True, splits=SPLITS) -> dict:
    """Draw, validate and write the splits (default both); returns the manifest (also suite.json).
    A split's files depend only on the seed and their own index, so a split written alone is the
    one both would give; the splits not written are kept from an existing manifest of the same
    suite and seed."""
    from tqdm import tqdm

    import tomli_w

    out.mkdir(parents=True, exist_ok=True)
    man_path = out / "suite.json"
    prev = json.loads(man_path.read_text()) if man_path.is_file() else {}
    manifest = {"name": ff.name, "families": [f.name for f in ff.families], "seed": seed,
                "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "splits": {}, "redrawn": {}}
    if prev.get("name") == ff.name and prev.get("seed") == seed:
        for split in SPLITS:
            if split not in splits and split in prev.get("splits", {}):
                manifest["splits"][split] = prev["splits"][split]
                manifest["redrawn"][split] = prev.get("redrawn", {}).get(split, {})
    for si, split in enumerate(SPLITS):
        if split not in splits:
            continue
        (out / split).mkdir(exist_ok=True)
        for old in (out / split).glob("*.toml"):
            old.unlink()
        counts = _counts(ff, n_test if split == "test" else n_train)
        entries = []
        bar = tqdm(total=sum(counts.values()), desc=f"suite {ff.name} {split}", unit="file",
                   disable=not progress)
        for fi, fam in enumerate(ff.families):
            pending = list(range(counts[fam.name]))
            attempt = {i: 0 for i in pending}
            redrawn = 0
            while pending:
                batch = []
                for i in pending:
                    rng = np.random.default_rng([seed, si, fi, i, attempt[i]])
                    name = f"{fam.name}-{i:04d}"
                    data = scenario_data(draw(rng, ff.common, fam), ff.common, fam, name)
                    batch.append((i, data, Scenario.model_validate(data)))
                ok = np.ones(len(batch), bool)
                for dy in VALIDATION_SHIFTS if ff.validate_conflicts else ():  # a margin: no near miss passes for a conflict
                    shifted = [b[2].ego_shifted(dy) for b in batch]
                    ok &= straight_collisions(shifted, seed=seed + 7919 * si).all(axis=1)
                pending = []
                for (i, data, _sc), good in zip(batch, ok):
                    if good:
                        path = out / split / f"{data['name']}.toml"
                        path.write_text(f"# generated by `racecav suite generate` (family {fam.name}, "
                                        f"split {split}, seed {[seed, si, fi, i, attempt[i]]})\n"
                                        + tomli_w.dumps(data))
                        entries.append({"file": f"{split}/{path.name}", "family": fam.name,
                                        "seed": [seed, si, fi, i, attempt[i]]})
                        bar.update(1)
                    else:
                        attempt[i] += 1
                        redrawn += 1
                        if attempt[i] >= MAX_ATTEMPTS:
                            raise RuntimeError(f"family {fam.name}: no valid draw in {MAX_ATTEMPTS} attempts")
                        pending.append(i)
            manifest["redrawn"].setdefault(split, {})[fam.name] = redrawn
        bar.close()
        manifest["splits"][split] = sorted(entries, key=lambda e: e["file"])
    manifest["splits"] = {k: manifest["splits"][k] for k in SPLITS if k in manifest["splits"]}
    man_path.write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest
