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

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from racecav.common.vehicle import format_errors

SCENARIOS_DIR = Path(__file__).parent / "data" / "scenarios"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class EgoStart(_Strict):
    """The ego car's start (world frame)."""

    x: float
    y: float
    yaw_deg: float
    speed: float = Field(0.0, ge=0)
    """Initial forward speed (m/s); the friction-model wheel state starts at speed / wheel_radius."""


class ObstacleSpec(_Strict):
    """An obstacle car at constant speed (kinematic: it does not react)."""

    x: float
    y: float
    yaw_deg: float
    speed: float = Field(ge=0)
    """m/s, held constant once moving."""
    delay_s: float = Field(0.0, ge=0)
    """Time (s) it stands still at its start before moving."""
    path: list[tuple[float, float]] = []
    """Optional waypoints (world frame) driven after the start point; empty = straight along yaw."""


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
    """Traffic driver name (racecav.services.sim.traffic)."""
    min_gap_m: float = Field(1.5, gt=0)
    """Minimum arc-length gap between any two cars at the start."""


class Success(_Strict):
    min_progress_m: float = Field(ge=0)
    """Minimum ego progress (m) for a collision-free trial to count as a success."""


class Scenario(_Strict):
    """Schema of a scenario file (see docs/world.md)."""

    name: str
    description: str = ""
    world: str
    """World name (common/data/worlds) or path."""
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
        return self

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
            obs.append(TrialObstacle(
                x=o.x + rng.uniform(-r.obstacle_xy, r.obstacle_xy),
                y=o.y + rng.uniform(-r.obstacle_xy, r.obstacle_xy),
                yaw=math.radians(o.yaw_deg + rng.uniform(-r.obstacle_yaw_deg, r.obstacle_yaw_deg)),
                speed=max(0.0, o.speed + rng.uniform(-r.obstacle_speed, r.obstacle_speed)),
                delay_s=o.delay_s + rng.uniform(0, r.obstacle_delay_s),
                path=np.asarray(o.path, dtype=np.float64).reshape(-1, 2)))
        return Trial(scenario=self, ego=ego, obstacles=obs)


@dataclass(frozen=True)
class TrialObstacle:
    """A concrete obstacle of one trial (radians, SI)."""

    x: float
    y: float
    yaw: float
    speed: float
    delay_s: float
    path: np.ndarray
    """(P, 2) waypoints after the start point; empty = straight along yaw."""

    def pose_at(self, t: float) -> tuple[float, float, float]:
        """Pose (x, y, yaw) at trial time t: still until delay_s, then constant speed."""
        dist = max(0.0, t - self.delay_s) * self.speed
        if len(self.path) == 0:
            return (self.x + dist * math.cos(self.yaw), self.y + dist * math.sin(self.yaw), self.yaw)
        pts = np.vstack([[self.x, self.y], self.path])
        yaw = self.yaw
        for a, b in zip(pts[:-1], pts[1:]):
            seg = float(np.hypot(*(b - a)))
            yaw = math.atan2(b[1] - a[1], b[0] - a[0])
            if dist <= seg:
                p = a + (b - a) * (dist / max(seg, 1e-12))
                return float(p[0]), float(p[1]), yaw
            dist -= seg
        # past the last waypoint: continue straight along the last segment's direction
        return (float(pts[-1][0] + dist * math.cos(yaw)), float(pts[-1][1] + dist * math.sin(yaw)), yaw)


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
    path = Path(name_or_path)
    if not path.suffix:
        path = SCENARIOS_DIR / f"{name_or_path}.toml"
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"scenario file {path}: not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"scenario file {path}: invalid TOML: {e}") from None
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        raise ValueError(f"scenario file {path}: {format_errors(e)}") from None


def scenario_names() -> list[str]:
    """Names of the shipped scenarios."""
    return sorted(p.stem for p in SCENARIOS_DIR.glob("*.toml"))
