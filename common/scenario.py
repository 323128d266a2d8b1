"""Scenarios: a world, the ego's start, obstacle cars, randomisation and success, as TOML data.

Two families share one schema:
- intersection trials (the paper's evaluation): ``[ego]`` start pose and speed, ``[[obstacles]]``
  moving at constant speed (straight along their yaw, or along ``path``) after ``delay_s``;
- the racetrack (training world): ``[traffic]`` places ``cars`` obstacle cars lapping the loop
  under a driver; the ego starts on the centerline with (or, ``heading = "reversed"``, against)
  the traffic.
A trial succeeds when the ego touches nothing during ``duration_s`` AND makes at least
``success.min_progress_m`` of progress (along its initial heading; along the centerline in the
ego's driving direction on a loop), so a car that never moves does not succeed.

Files: common/data/scenarios/NAME.toml; every field is documented in docs/world.md. Unknown or
invalid fields are errors naming the field.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from racecav.common.vehicle import load_toml
from racecav.common.world import World, WorldFile, build_world, load_world, plot_world

SCENARIOS_DIR = Path(__file__).parent / "data" / "scenarios"
SUITES_RUNS_DIR = Path("runs/suites")
"""Generated conflict suites (``racecav suite generate``): runs/suites/NAME/{train,test}/, suite.json."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class EgoStart(_Strict):
    """The ego car's start (world frame)."""

    x: float
    y: float
    yaw_deg: float
    speed: float = Field(0.0, ge=0)
    """Initial forward speed (m/s); the friction-model wheel state starts at speed / wheel_radius."""


Point = tuple[float, float]


class StartTrigger(_Strict):
    """When an obstacle starts moving (esmini TimeToCollisionCondition / CARLA
    InTimeToArrivalToLocation). Until then it stands at its start."""

    kind: Literal["time", "time_to_arrival", "distance"] = "time"
    """time: ``value`` s of sim time; time_to_arrival: the ego's distance to ``point`` divided
    by its current speed is <= ``value`` s; distance: the ego is within ``value`` m of ``point``."""
    value: float = Field(0.0, ge=0)
    point: Point = (0.0, 0.0)
    """World-frame point (m) the ego's arrival is measured to (time_to_arrival, distance)."""


class Sync(_Strict):
    """Synchronised arrival (CARLA SyncArrival, esmini SynchronizeAction with the ego as master):
    each control period the obstacle's speed is re-solved so that it reaches ``actor_point``
    when the ego reaches ``ego_point`` at its current speed, clamped to [speed_min, speed_max];
    released to constant speed once the ego is within ``release_distance_m`` or
    ``release_time_s`` of its point (an ego that brakes or swerves late is not chased)."""

    ego_point: Point
    actor_point: Point
    """A point on the obstacle's path (projected onto it)."""
    speed_min: float = Field(0.5, ge=0)
    speed_max: float = Field(2.0, gt=0)
    release_distance_m: float = Field(1.0, ge=0)
    release_time_s: float = Field(0.8, ge=0)
    release_stopped_s: float | None = Field(None, ge=0)
    """Also released, to its nominal ``speed``, once the ego has stood still (< 0.05 m/s) this
    long: an ego that yields is not kept waiting by an actor crawling at ``speed_min``
    (default: never)."""

    @model_validator(mode="after")
    def _range(self) -> "Sync":
        if self.speed_min > self.speed_max:
            raise ValueError("speed_min: must not exceed speed_max")
        return self


class SpeedChange(_Strict):
    """Past ``at_m`` metres along its path the obstacle changes speed towards ``speed`` at
    ``accel`` m/s^2 (e.g. brakes to a stop in the crossing). Ends any synchronisation."""

    at_m: float = Field(ge=0)
    speed: float = Field(ge=0)
    accel: float = Field(gt=0)


class ObstacleSpec(_Strict):
    """An obstacle car (kinematic: it does not react to contacts); see sim/actors.py."""

    x: float
    y: float
    yaw_deg: float
    speed: float = Field(ge=0)
    """m/s once moving (until a synchronisation or a speed change sets another)."""
    delay_s: float = Field(0.0, ge=0)
    """Time (s) it stands still at its start before moving (shorthand for a time trigger)."""
    path: list[Point] = []
    """Optional waypoints (world frame) driven after the start point; empty = straight along yaw."""
    start: StartTrigger | None = None
    """Start trigger (default: time = delay_s)."""
    sync: Sync | None = None
    speed_changes: list[SpeedChange] = []

    @model_validator(mode="after")
    def _one_start(self) -> "ObstacleSpec":
        if self.start is not None and self.delay_s > 0:
            raise ValueError("delay_s: give either delay_s or [start], not both")
        return self

    @property
    def conflict_timed(self) -> bool:
        """Timed by the ego (a condition trigger or a synchronised arrival), not by the clock."""
        return self.sync is not None or (self.start is not None and self.start.kind != "time")


class Randomize(_Strict):
    """Per-trial uniform perturbations (+- the value; delay: + [0, value])."""

    ego_xy: float = Field(0.0, ge=0)
    """m, along x and y independently."""
    ego_yaw_deg: float = Field(0.0, ge=0)
    ego_speed: float = Field(0.0, ge=0)
    obstacle_xy: float = Field(0.0, ge=0)
    obstacle_yaw_deg: float = Field(0.0, ge=0)
    obstacle_speed: float = Field(0.0, ge=0)
    obstacle_delay_s: float = Field(0.0, ge=0)
    """Extra start delay drawn from [0, value] (timing of the conflict)."""


class Traffic(_Strict):
    """Obstacle cars lapping a loop world."""

    cars: int = Field(15, ge=0, le=63)
    heading: Literal["default", "reversed"] = "default"
    """default: the ego drives with the traffic; reversed: against it (paper's reversed heading)."""
    driver: str = "pure_pursuit"
    """Traffic driver name (racecav.sim.traffic)."""
    min_gap_m: float = Field(1.5, gt=0)
    """Minimum arc-length gap between any two cars at the start."""


class Success(_Strict):
    min_progress_m: float = Field(ge=0)
    """Minimum ego progress (m) for a collision-free trial to count as a success."""


class Scenario(_Strict):
    """Schema of a scenario file (see docs/world.md)."""

    name: str
    description: str = ""
    world: str | None = None
    """World name (common/data/worlds) or path; or, instead, the world inline in ``[map]``."""
    map: WorldFile | None = None
    """The world itself (a world file's fields): a generated file carries its road, so the
    file's digest covers it."""
    duration_s: float = Field(gt=0)
    ego: EgoStart | None = None
    """Required unless the world is a loop with [traffic] (then placed on the centerline)."""
    obstacles: list[ObstacleSpec] = []
    traffic: Traffic | None = None
    randomize: Randomize = Randomize()
    success: Success
    seed: int = 0
    """Default seed of the trial sequence (the CLI/caller may override)."""

    @model_validator(mode="after")
    def _check(self) -> "Scenario":
        if self.ego is None and self.traffic is None:
            raise ValueError("ego: required when there is no [traffic] section")
        if self.traffic is not None and self.obstacles:
            raise ValueError("obstacles: not allowed together with [traffic]")
        if (self.world is None) == (self.map is None):
            raise ValueError("world: give either world (a name or path) or [map], not both or neither")
        return self

    @property
    def world_key(self) -> str:
        """What identifies its geometry: the world's name, or ``map:`` and a digest of [map]
        (scenarios with one key share one world)."""
        if self.map is None:
            return self.world
        return "map:" + hashlib.sha1(self.map.model_dump_json().encode()).hexdigest()[:16]

    def build_world(self) -> World:
        """Its world, for either backend (built once per key and process)."""
        key = self.world_key
        if key not in _WORLDS:
            if len(_WORLDS) > 256:
                _WORLDS.clear()
            try:
                _WORLDS[key] = load_world(self.world) if self.map is None else build_world(self.map)
            except ValueError as e:
                raise ValueError(f"scenario {self.name}: map: {e}" if self.map is not None else str(e)) from None
        return _WORLDS[key]

    def ego_shifted(self, dy: float) -> "Scenario":
        """The scenario with its ego starting ``dy`` metres to its left."""
        if not dy:
            return self
        e = self.ego
        return self.model_copy(update={"ego": e.model_copy(update={
            "x": e.x - dy * math.sin(math.radians(e.yaw_deg)), "y": e.y + dy * math.cos(math.radians(e.yaw_deg))})})

    def sample(self, rng: np.random.Generator) -> "Trial":
        """Draw one concrete trial (randomisation applied) for an intersection-type scenario."""
        r = self.randomize
        ego = None
        if self.ego is not None:
            e = self.ego
            ego = (e.x + rng.uniform(-r.ego_xy, r.ego_xy), e.y + rng.uniform(-r.ego_xy, r.ego_xy),
                   math.radians(e.yaw_deg + rng.uniform(-r.ego_yaw_deg, r.ego_yaw_deg)),
                   max(0.0, e.speed + rng.uniform(-r.ego_speed, r.ego_speed)))
        obs = []
        for o in self.obstacles:
            x = o.x + rng.uniform(-r.obstacle_xy, r.obstacle_xy)
            y = o.y + rng.uniform(-r.obstacle_xy, r.obstacle_xy)
            yaw = math.radians(o.yaw_deg + rng.uniform(-r.obstacle_yaw_deg, r.obstacle_yaw_deg))
            speed = max(0.0, o.speed + rng.uniform(-r.obstacle_speed, r.obstacle_speed))
            delay = rng.uniform(0, r.obstacle_delay_s)  # drawn for every obstacle: same stream
            start = o.start or StartTrigger(kind="time", value=o.delay_s + delay)
            obs.append(TrialObstacle(x=x, y=y, yaw=yaw, speed=speed, start=start, sync=o.sync,
                                     speed_changes=tuple(o.speed_changes),
                                     path=np.asarray(o.path, dtype=np.float64).reshape(-1, 2)))
        return Trial(scenario=self, ego=ego, obstacles=obs)

    @property
    def conflict_timed(self) -> bool:
        """Some obstacle is timed by the ego (trigger or synchronised arrival)."""
        return any(o.conflict_timed for o in self.obstacles)


_WORLDS: dict[str, World] = {}


@dataclass(frozen=True)
class TrialObstacle:
    """A concrete obstacle of one trial (radians, SI); sim/actors.py moves it."""

    x: float
    y: float
    yaw: float
    speed: float
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """(P, 2) waypoints after the start point; empty = straight along yaw."""
    start: StartTrigger = StartTrigger()
    sync: Sync | None = None
    speed_changes: tuple[SpeedChange, ...] = ()


@dataclass(frozen=True)
class Trial:
    """One concrete trial drawn by :meth:`Scenario.sample`."""

    scenario: Scenario
    ego: tuple[float, float, float, float] | None
    """x, y, yaw (rad), speed (m/s); None = placed by the world (racetrack)."""
    obstacles: list[TrialObstacle]


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a scenario by name (common/data/scenarios/NAME.toml) or from a TOML file path.

    :raises ValueError: naming the file and the invalid field.
    """
    return load_toml(name_or_path, SCENARIOS_DIR, Scenario, "scenario")


def scenario_names() -> list[str]:
    """Names of the shipped scenarios."""
    return sorted(p.stem for p in SCENARIOS_DIR.glob("*.toml"))


@dataclass(frozen=True)
class Suite:
    """A generated suite on disk."""

    root: Path
    manifest: dict

    def files(self, split: str) -> list[tuple[Path, str]]:
        """(scenario file, family) of a split.

        :raises ValueError: the split was not generated (names the command that writes it)."""
        if split not in self.manifest["splits"]:
            raise ValueError(f"suite {self.root}: no {split} split (have {', '.join(self.manifest['splits'])}; "
                             f"write it with `racecav suite generate --name {self.manifest['name']} --splits {split}`)")
        return [(self.root / e["file"], e["family"]) for e in self.manifest["splits"][split]]

    @property
    def families(self) -> list[str]:
        return list(self.manifest["families"])


def open_suite(name_or_dir: str | Path) -> Suite:
    """A generated suite by name (runs/suites/NAME) or folder (holding suite.json).

    :raises ValueError: naming the folder when it holds no suite.
    """
    root = Path(name_or_dir)
    if not (root / "suite.json").is_file():
        root = SUITES_RUNS_DIR / str(name_or_dir)
    man = root / "suite.json"
    if not man.is_file():
        raise ValueError(f"suite {name_or_dir}: no suite.json in {root} "
                         f"(make it with `racecav suite generate --name {name_or_dir}`)")
    try:
        return Suite(root, json.loads(man.read_text()))
    except json.JSONDecodeError as e:
        raise ValueError(f"suite {man}: invalid JSON: {e}") from None


def unfiltered(spec: str) -> str:
    """The suite a filtered suite was cut from (its suite.json's ``filtered_from``, written by
    ``racecav train seen-filter``), else ``spec``: selection scores the whole source, never the
    filtered training mix."""
    try:
        return open_suite(spec).manifest.get("filtered_from", spec)
    except ValueError:  # a folder or file of scenarios, not a suite
        return spec


def scenario_sources(spec: str | Path, split: str = "train") -> list[tuple[Path, str]]:
    """(file, family) of a suite's split (suite NAME or folder with suite.json; family
    "<suite folder>/<family>" from its manifest), of a folder (every *.toml in it) or of one
    file (family: the file's stem); several of these separated by commas.

    :raises ValueError: when nothing is found, naming what was looked for.
    """
    if "," in str(spec):
        return [x for part in str(spec).split(",") if part.strip() for x in scenario_sources(part.strip(), split)]
    p = Path(spec)
    if p.is_file():
        return [(p, p.stem)]
    if p.is_dir() and not (p / "suite.json").is_file():
        files = sorted(p.glob("*.toml"))
        if not files:
            raise ValueError(f"scenarios {p}: no *.toml files in the folder")
        return [(f, f.stem) for f in files]
    suite = open_suite(spec)
    return [(f, f"{suite.root.name}/{fam}") for f, fam in suite.files(split)]


def scenario_files(spec: str | Path, split: str = "train") -> list[Path]:
    """The files of ``scenario_sources(spec, split)``."""
    return [f for f, _fam in scenario_sources(spec, split)]


def main(argv: list[str] | None = None) -> int:
    """``python -m racecav.common.scenario OUT.png [WORLD...]``: plot worlds with the start poses of the
    scenarios played in them (docs/world.md figure; here, not in world.py, which scenarios import)."""
    import sys

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args = sys.argv[1:] if argv is None else argv
    if not args:
        print("usage: python -m racecav.common.scenario OUT.png [WORLD ...]")
        return 2
    names = args[1:] or ["racetrack", "figure8", "intersection"]
    fig, axes = plt.subplots(1, len(names), figsize=(7 * len(names), 5))
    for ax, name in zip(np.atleast_1d(axes), names):
        plot_world(load_world(name), ax)
        # the start poses of the scenarios played in this world (ego green, obstacles red)
        for sc in (load_scenario(n) for n in scenario_names()):
            if sc.world != name or sc.ego is None:
                continue
            for pose, color, label in [((sc.ego.x, sc.ego.y, sc.ego.yaw_deg), "g", "ego"),
                                       *(((o.x, o.y, o.yaw_deg), "r", sc.name) for o in sc.obstacles)]:
                x, y, yaw = pose[0], pose[1], math.radians(pose[2])
                ax.annotate("", xy=(x + math.cos(yaw), y + math.sin(yaw)), xytext=(x, y),
                            arrowprops=dict(arrowstyle="->", color=color, lw=2))
                ax.text(x + 0.2, y + 0.3, label, color=color, fontsize=8)
    fig.tight_layout()
    fig.savefig(args[0], dpi=90)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
