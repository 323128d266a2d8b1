"""Messages exchanged on the bus (pydantic v2 models, ROS REP-103 units and frames).

SI units, radians, right-handed frames; body x forward, y left; angles counter-clockwise with 0
straight ahead. Stamps are integer nanoseconds: monotonic clock on the car, sim time in the
simulator (never mixed in one run). Every message carries ``stamp_ns`` and ``seq``; the wire
format (msgpack, schema version, float32 arrays) is :mod:`racecav.common.codec`.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PlainSerializer, model_validator


def _as_float32(v: Any) -> np.ndarray:
    if isinstance(v, (bytes, bytearray, memoryview)):
        if len(v) % 4:
            raise ValueError("float32 array bytes not a multiple of 4")
        return np.frombuffer(v, dtype="<f4")
    if isinstance(v, (list, tuple)):  # JSON form; strict: numbers only, no bools or strings
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            raise ValueError("expected a list of numbers")
    elif not isinstance(v, np.ndarray):
        raise ValueError(f"expected float32 bytes or a list of numbers, got {type(v).__name__}")
    with np.errstate(over="ignore", invalid="ignore"):
        wide = np.asarray(v, dtype=np.float64)
        arr = wide.astype(np.float32)
    if arr.ndim != 1:
        raise ValueError(f"expected a 1-D array, got shape {arr.shape}")
    if (np.isinf(arr) & np.isfinite(wide)).any():
        raise ValueError("value beyond the float32 range")
    return arr


Float32Array = Annotated[
    np.ndarray,
    BeforeValidator(_as_float32),
    PlainSerializer(lambda a: a.tolist(), when_used="json"),
]
"""1-D float32 array: raw little-endian bytes on the wire, a list in JSON."""

Finite = Annotated[float, Field(allow_inf_nan=False)]

INT64_MAX = 2**63 - 1
"""Every integer on the wire fits a signed 64-bit integer (ROS builtin_interfaces, msgpack int64)."""

Stamp = Annotated[int, Field(ge=0, le=INT64_MAX)]
Count = Annotated[int, Field(ge=0, le=INT64_MAX)]
Coord = Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)]
"""A position (m) or velocity: finite and within 1,000 km (anything beyond is a broken producer)."""
Angle = Annotated[float, Field(allow_inf_nan=False, ge=-4 * math.pi, le=4 * math.pi)]
"""An angle (rad): finite, within two turns either way."""
Name = Annotated[str, Field(min_length=1, max_length=64)]

MIN_ANGLE_INCREMENT = 1e-5
"""rad: the finest scan increment accepted (0.0006 deg; real lidars are above 0.05 deg)."""
MAX_RAYS = 16384
"""Rays in one scan at most (a 64 KiB payload holds 16,384 float32 values)."""


class Message(BaseModel):
    """Base of every message."""

    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True, frozen=False)
    TYPE: ClassVar[str] = ""

    stamp_ns: Stamp
    seq: Count = 0


class Scan(Message):
    """A planar laser scan; mirrors sensor_msgs/LaserScan.

    The policy's observation is such a scan: 170 rays, angle_min = -pi/4, angle_max = +pi/4,
    counter-clockwise (ranges[0] is the rightmost ray). No return is +inf, never 0; NaN is
    invalid. ``stamp_ns`` is the time of the first ray.
    """

    TYPE: ClassVar[str] = "scan"
    frame_id: Name = "laser"
    source: Literal["sim", "real"]
    angle_min: Angle
    angle_max: Angle
    angle_increment: Finite = Field(ge=MIN_ANGLE_INCREMENT, le=2 * math.pi)
    time_increment: Finite = Field(0.0, ge=-1.0, le=1.0)
    scan_time: Finite = Field(0.0, ge=0.0, le=60.0)
    range_min: Finite = Field(ge=0, le=1e4)
    range_max: Finite = Field(gt=0, le=1e4)
    ranges: Float32Array
    intensities: Float32Array = Field(default_factory=lambda: np.zeros(0, np.float32))

    @model_validator(mode="after")
    def _check(self) -> "Scan":
        if self.angle_max < self.angle_min:
            raise ValueError("angle_max is below angle_min")
        # bounded angles and increment: the ray count is at most 8 pi / 1e-5, round() is safe
        n = round((self.angle_max - self.angle_min) / self.angle_increment) + 1
        if n > MAX_RAYS:
            raise ValueError(f"angles imply {n} rays, more than {MAX_RAYS}")
        if self.ranges.shape[0] != n:
            raise ValueError(f"ranges has {self.ranges.shape[0]} values, angles imply {n}")
        if np.isnan(self.ranges).any():
            raise ValueError("ranges contain NaN (no return must be +inf)")
        if (self.ranges < 0).any():
            raise ValueError("ranges contain negative values")
        if self.intensities.shape[0] not in (0, n):
            raise ValueError("intensities must be empty or as long as ranges")
        return self

    def angles(self) -> np.ndarray:
        """Ray angles in the laser frame (rad)."""
        return (self.angle_min + self.angle_increment * np.arange(self.ranges.shape[0])).astype(np.float32)


THROTTLE_TOL = 1e-3
"""Largest accepted difference between a DriveCommand's throttle and clip(a_throttle, 0, 1)."""


class DriveCommand(Message):
    """What a controller asks of the car, in both the policy's and the physical meaning.

    Like ackermann_msgs/AckermannDrive, positive steering is left. ``scan_seq``/``scan_stamp_ns``
    name the scan this command answers, so latency can be traced end to end; ``compute_ns`` is the
    controller's own compute time for it.
    """

    TYPE: ClassVar[str] = "cmd"
    source: Name
    """Controller that produced it: policy, baseline, teleop, ..."""
    a_throttle: Finite = Field(ge=-1, le=1)
    """Normalised throttle action a_T in [-1, 1] as the policy outputs it."""
    a_steer: Finite = Field(ge=-1, le=1)
    """Normalised steering action a_delta in [-1, 1]."""
    throttle: Finite = Field(ge=0, le=1)
    """Physical throttle T = clip(a_T, 0, 1)."""
    steering_angle: Finite = Field(ge=-math.pi / 2, le=math.pi / 2)
    """Front wheel angle (rad), within the car's [delta_min, delta_max]."""
    scan_seq: int = Field(-1, ge=-1, le=INT64_MAX)
    scan_stamp_ns: int = Field(-1, ge=-1, le=INT64_MAX)
    compute_ns: Count = 0
    scan_source: Literal["", "sim", "real"] = ""
    """Source of the scan this command answers ("" = not an answer to a scan, e.g. teleop): the
    actuator refuses answers to simulator scans unless ``actuator.sim_scans_drive``."""
    brake: bool = False
    """Brake (the VESC's brake current; wheel speed target 0 in the sim) instead of coasting.
    Set by policies trained with a brake action (a_T below their ``brake_below``); requires
    throttle 0."""

    @model_validator(mode="after")
    def _consistent(self) -> "DriveCommand":
        # The two meanings must agree: an actuator applies the physical fields, a log reader
        # trusts the normalised ones; a command where they disagree is a broken producer.
        if abs(self.throttle - min(max(self.a_throttle, 0.0), 1.0)) > THROTTLE_TOL:
            raise ValueError(f"throttle {self.throttle} contradicts a_throttle {self.a_throttle} "
                             f"(throttle = clip(a_throttle, 0, 1))")
        if self.brake and self.throttle > THROTTLE_TOL:
            raise ValueError(f"brake with throttle {self.throttle}: a braking command has throttle 0")
        if self.a_steer * self.steering_angle < 0:
            raise ValueError(f"steering_angle {self.steering_angle} and a_steer {self.a_steer} "
                             f"have opposite signs")
        return self


class VehicleState(Message):
    """Pose in the world frame and body-frame velocities (sim ground truth or odometry)."""

    TYPE: ClassVar[str] = "state"
    frame_id: Name = "odom"
    source: Literal["sim", "real"]
    x: Coord
    y: Coord
    yaw: Angle
    vx: Coord = 0.0
    """Body-frame forward velocity (m/s)."""
    vy: Coord = 0.0
    """Body-frame lateral velocity (m/s), positive left."""
    yaw_rate: Coord = 0.0
    steering_angle: Angle = 0.0
    collided: bool = False


class Obstacle(BaseModel):
    """One obstacle car (ground truth)."""

    model_config = ConfigDict(extra="forbid")
    id: int = Field(ge=0, le=INT64_MAX)
    x: Coord
    y: Coord
    yaw: Angle
    speed: Coord = 0.0
    length: Finite = Field(0.55, gt=0, le=100)
    width: Finite = Field(0.3, gt=0, le=100)


class ObstacleStates(Message):
    """Ground-truth obstacle cars, published by the simulator only (diagnosis, oracle baselines)."""

    TYPE: ClassVar[str] = "obstacles"
    frame_id: Name = "odom"
    source: Literal["sim"] = "sim"
    obstacles: list[Obstacle] = Field(default_factory=list, max_length=256)


class ServiceStatus(Message):
    """Answer of racecav/<car>/<service>/status."""

    TYPE: ClassVar[str] = "status"
    service: Name
    car: Name
    pid: Count = 0
    uptime_s: Finite = Field(0.0, ge=0)
    received: Count = 0
    published: Count = 0
    invalid: Count = 0
    dropped: Count = 0
    errors: Count = 0
    """Exceptions caught in the service's callbacks, queries and loop (it kept running)."""
    last_error: str = Field("", max_length=4096)
    config_digest: str = ""
    info: dict[str, Any] = Field(default_factory=dict)
    """Service-specific state (mode, scenario, source, solver stats, ...), JSON-able."""
    outputs: dict[str, Any] = Field(default_factory=dict)
    """Latest published message per key, as JSON-able dicts."""


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls for cls in (Scan, DriveCommand, VehicleState, ObstacleStates, ServiceStatus)
}
