"""The car: its parameters (one data file per car) and the actuation functions every backend shares.

Car frame (REP-103 base_link): origin on the ground midway between the front and rear axles, x
forward, y left, z up. The pose (x, y, yaw) of a car anywhere in the project is this frame's.

The three functions below are the single definition of how an action becomes actuation; the
PyBullet world, the fast batched world and the real actuator all call them.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from racecav.common.lidar import LidarSpec

CARS_DIR = Path(__file__).parent / "data" / "cars"


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MountPose(_Frozen):
    """A sensor pose in the car frame."""

    x: float = 0.20
    y: float = 0.0
    z: float = 0.19
    yaw: float = 0.0


class BicycleParams(_Frozen):
    """Single-track model of the fast backend; fitted to PyBullet rollouts by its fit script."""

    fitted: bool = False
    """True once the values come from a fit (see the fit script's note in the car file)."""
    lf: float = Field(0.1625, gt=0)
    """CoG to front axle (m)."""
    lr: float = Field(0.1625, gt=0)
    """CoG to rear axle (m)."""
    iz: float = Field(0.074, gt=0)
    """Yaw inertia (kg m^2)."""
    mu: float = Field(1.0, gt=0)
    c_sf: float = Field(4.718, gt=0)
    """Front cornering stiffness coefficient (1/rad)."""
    c_sr: float = Field(5.4562, gt=0)
    """Rear cornering stiffness coefficient (1/rad)."""
    steer_tau: float = Field(0.0, ge=0)
    """First-order steering lag (s) on top of the rate limit; 0 = none."""
    speed_tau: float = Field(0.0, ge=0)
    """Lag of body speed behind wheel speed (s); 0 = none."""
    scrub: float = Field(0.0, ge=0)
    """Speed loss in turns of the fast model: v = v_wheel * (1 - scrub * tan(delta)^2 - ...)."""
    scrub_lat: float = Field(0.0, ge=0)
    """... - scrub_lat * |lateral acceleration| (s^2/m): drag of slipping tyres."""
    c_speed_inv: float = 0.0
    """Cornering stiffnesses scale with 1 + c_speed_inv * (1 m/s / v - 1); 0 = constant, 1 = inversely
    with speed."""
    heading_c4: float = 0.0
    """Heading-dependent grip: the tyres see delta * (1 + heading_c4 cos 4psi + heading_s4 sin 4psi),
    psi the yaw (-yaw in right turns). PyBullet's grip depends on the heading relative to the
    world axes (period 90 deg); 0 = isotropic."""
    heading_s4: float = 0.0
    """See heading_c4."""
    brake_decel: float = Field(9.7, gt=0)
    """Deceleration (m/s^2) of a braking car (wheel speed target 0). PyBullet's velocity motor
    locks the wheels and they skid at about mu g: 2.0 -> 0 m/s in 0.2 s, 0.18 m, heading held."""


class CarParams(_Frozen):
    """Every physical parameter of a car (see common/data/cars/slash.toml for the reasons)."""

    name: str
    wheelbase: float = Field(gt=0)
    track: float = Field(gt=0)
    length: float = Field(gt=0)
    width: float = Field(gt=0)
    height: float = Field(gt=0)
    ground_clearance: float = Field(ge=0)
    mass: float = Field(gt=0)
    com_height: float = Field(0.06, gt=0)
    """Centre of mass above the ground (m)."""
    wheel_radius: float = Field(gt=0)
    wheel_width: float = Field(gt=0)
    wheel_mass: float = Field(gt=0)
    tire_friction: float = Field(gt=0)
    delta_min: float = Field(lt=0)
    """Steering limit to the right (rad, negative)."""
    delta_max: float = Field(gt=0)
    """Steering limit to the left (rad, positive)."""
    steer_gain: float = Field(1.0, gt=0)
    """rad per unit of a_delta before clipping (1.0 = the paper's mapping)."""
    steer_rate_max: float = Field(gt=0)
    """Servo slew limit (rad/s)."""
    throttle_gain: float = Field(gt=0)
    throttle_c_quad: float = Field(ge=0)
    throttle_c_lin: float = Field(ge=0)
    wheel_max_torque: float = Field(gt=0)
    driven_wheels: str = Field(pattern="^(all|rear)$")
    agent_speed_scale: float = Field(gt=0)
    """The racetrack agent's wheel velocity target is this times the friction-model state."""
    control_period_s: float = Field(gt=0)
    physics_substeps: int = Field(ge=1)
    lidar_mount: MountPose = MountPose()
    lidar: LidarSpec = LidarSpec()
    bicycle: BicycleParams = BicycleParams()

    @model_validator(mode="after")
    def _check(self) -> "CarParams":
        if self.track + self.wheel_width > self.width + 1e-9:
            raise ValueError("width: must cover track + wheel_width")
        if self.wheelbase + 2 * self.wheel_radius > self.length + 1e-9:
            raise ValueError("length: must cover wheelbase + 2 * wheel_radius")
        return self

    def ray_start_offsets(self, angles: np.ndarray) -> np.ndarray:
        """Distance (m) from the lidar mount along each ray (car-frame angles) to where it leaves
        the car's own body box: rays start there so a car never sees itself."""
        m = self.lidar_mount
        c, s = np.cos(angles + m.yaw), np.sin(angles + m.yaw)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (self.length / 2 - m.x) / c, np.where(c < 0, (-self.length / 2 - m.x) / c, np.inf))
            ty = np.where(s > 0, (self.width / 2 - m.y) / s, np.where(s < 0, (-self.width / 2 - m.y) / s, np.inf))
        return np.maximum(np.minimum(tx, ty), 0.0)

    @property
    def physics_dt(self) -> float:
        """Physics step (s): the control period split into ``physics_substeps``."""
        return self.control_period_s / self.physics_substeps

    @property
    def w_max(self) -> float:
        """Steady-state wheel speed (rad/s) of the friction model at full throttle."""
        a, b, c = self.throttle_c_quad, self.throttle_c_lin, -self.throttle_gain
        return float((-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)) if a > 0 else self.throttle_gain / b

    @property
    def v_max(self) -> float:
        """Top speed (m/s) of an obstacle car: w_max * wheel_radius."""
        return self.w_max * self.wheel_radius


def load_toml(name_or_path: str | Path, folder: Path, model: type[M], what: str) -> M:
    """A TOML data file validated by a pydantic model: by name (``folder/NAME.toml``) or path.
    The one loader of car, world, scenario and family files.

    :raises ValueError: naming the file and what is wrong (missing, not TOML or not UTF-8, the
        invalid field).
    """
    path = Path(name_or_path)
    if not path.suffix:
        path = folder / f"{name_or_path}.toml"
    try:
        data = tomllib.loads(path.read_text())
    except (FileNotFoundError, IsADirectoryError):
        raise ValueError(f"{what} file {path}: not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{what} file {path}: invalid TOML: {e}") from None
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise ValueError(f"{what} file {path}: {format_errors(e)}") from None


def load_car(name_or_path: str | Path = "slash") -> CarParams:
    """Load a car by name (common/data/cars/NAME.toml) or from a TOML file path.

    :raises ValueError: naming the file and the invalid field.
    """
    return load_toml(name_or_path, CARS_DIR, CarParams, "car")


M = TypeVar("M", bound=BaseModel)


def format_errors(e: ValidationError) -> str:
    """One line per invalid field: ``field.path: message (got value)``."""
    out = []
    for err in e.errors():
        field = ".".join(str(p) for p in err["loc"]) or "<root>"
        msg = err["msg"].removeprefix("Value error, ")
        out.append(f"{field}: {msg} (got {err.get('input')!r})" if err["type"] != "missing"
                   else f"{field}: field required")
    return "; ".join(out)


def wheel_speed_step(w, throttle, dt: float, car: CarParams):
    """AutoVRL's throttle friction model, one Euler step, floored at 0 (numpy-vectorised).

    ``w <- max(0, w + dt * (gain * T - w * (c_quad * w + c_lin)))``

    :param w: wheel speed state (rad/s), scalar or array.
    :param throttle: physical throttle T in [0, 1], same shape (or broadcastable).
    :param dt: integration step (s): the physics step, see the car file.
    :return: next wheel speed (rad/s).
    """
    w = np.asarray(w, dtype=np.float64)
    dw = car.throttle_gain * np.asarray(throttle) - w * (car.throttle_c_quad * w + car.throttle_c_lin)
    return np.maximum(w + dt * dw, 0.0)


def steady_speed(throttle, car: CarParams, speed_scale: float = 1.0):
    """Forward speed (m/s) the friction model settles at for a constant throttle T, for a car
    whose wheel velocity target is ``speed_scale * w`` (the agent: car.agent_speed_scale)."""
    a, b, g = car.throttle_c_quad, car.throttle_c_lin, car.throttle_gain
    t = np.asarray(throttle, dtype=np.float64)
    w = (-b + np.sqrt(b * b + 4 * a * g * t)) / (2 * a) if a > 0 else g * t / b
    return w * car.wheel_radius * speed_scale


def throttle_for_speed(speed, car: CarParams, speed_scale: float = 1.0):
    """The constant throttle T whose steady speed is ``speed`` (inverse of :func:`steady_speed`)."""
    w = np.asarray(speed, dtype=np.float64) / (car.wheel_radius * speed_scale)
    return np.clip(w * (car.throttle_c_quad * w + car.throttle_c_lin) / car.throttle_gain, 0.0, 1.0)


def throttle_from_action(a_throttle):
    """Physical throttle T = clip(a_T, 0, 1): the paper's mapping (no reverse, no brake)."""
    return np.clip(a_throttle, 0.0, 1.0)


def brake_from_action(a_throttle, brake_below: float | None):
    """True where the car brakes: a policy trained with a brake action (``brake_below``, e.g.
    -0.5) brakes when a_T < brake_below (wheel speed target 0 in the sim, the VESC's brake
    current on the car); throttle is then 0 as for any a_T <= 0. None: the paper's action, where
    a_T <= 0 only coasts (the friction model slows the car at ~0.5-1 m/s^2)."""
    a = np.asarray(a_throttle, dtype=np.float64)
    if brake_below is None:
        return np.zeros(a.shape, bool)
    return a < brake_below


def steer_from_action(a_steer, car: CarParams):
    """Front wheel angle (rad) = clip(steer_gain * a_delta, delta_min, delta_max).

    With steer_gain = 1 this is the paper's ``max(min(a_delta, delta_max), delta_min)``.
    """
    return np.clip(car.steer_gain * np.asarray(a_steer, dtype=np.float64), car.delta_min, car.delta_max)


def steer_rate_limit(current, target, dt: float, car: CarParams):
    """Move the steering angle towards ``target`` by at most ``steer_rate_max * dt``."""
    step = car.steer_rate_max * dt
    return np.asarray(current) + np.clip(np.asarray(target) - current, -step, step)
