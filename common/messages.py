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
    arr = np.asarray(v, dtype=np.float32)
    if arr.ndim != 1:
        raise ValueError(f"expected a 1-D array, got shape {arr.shape}")
    return arr


Float32Array = Annotated[
    np.ndarray,
    BeforeValidator(_as_float32),
    PlainSerializer(lambda a: a.tolist(), when_used="json"),
]
"""1-D float32 array: raw little-endian bytes on the wire, a list in JSON."""

Finite = Annotated[float, Field(allow_inf_nan=False)]


class Message(BaseModel):
    """Base of every message."""

    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True, frozen=False)
    TYPE: ClassVar[str] = ""

    stamp_ns: int = Field(ge=0)
    seq: int = Field(0, ge=0)


class Scan(Message):
    """A planar laser scan; mirrors sensor_msgs/LaserScan.

    The policy's observation is such a scan: 170 rays, angle_min = -pi/4, angle_max = +pi/4,
    counter-clockwise (ranges[0] is the rightmost ray). No return is +inf, never 0; NaN is
    invalid. ``stamp_ns`` is the time of the first ray.
    """

    TYPE: ClassVar[str] = "scan"
    frame_id: str = "laser"
    source: Literal["sim", "real"]
    angle_min: Finite
    angle_max: Finite
    angle_increment: Finite = Field(gt=0)
    time_increment: Finite = 0.0
    scan_time: Finite = 0.0
    range_min: Finite = Field(ge=0)
    range_max: Finite = Field(gt=0)
    ranges: Float32Array
    intensities: Float32Array = Field(default_factory=lambda: np.zeros(0, np.float32))

    @model_validator(mode="after")
    def _check(self) -> "Scan":
        n = round((self.angle_max - self.angle_min) / self.angle_increment) + 1
        if self.ranges.shape[0] != n:
            raise ValueError(f"ranges has {self.ranges.shape[0]} values, angles imply {n}")
        if np.isnan(self.ranges).any():
            raise ValueError("ranges contain NaN (no return must be +inf)")
        if self.intensities.shape[0] not in (0, n):
            raise ValueError("intensities must be empty or as long as ranges")
        return self

    def angles(self) -> np.ndarray:
        """Ray angles in the laser frame (rad)."""
        return (self.angle_min + self.angle_increment * np.arange(self.ranges.shape[0])).astype(np.float32)


class DriveCommand(Message):
    """What a controller asks of the car, in both the policy's and the physical meaning.

    Like ackermann_msgs/AckermannDrive, positive steering is left. ``scan_seq``/``scan_stamp_ns``
    name the scan this command answers, so latency can be traced end to end; ``compute_ns`` is the
    controller's own compute time for it.
    """

    TYPE: ClassVar[str] = "cmd"
    source: str = Field(min_length=1, max_length=64)
    """Controller that produced it: policy, baseline, teleop, ..."""
    a_throttle: Finite = Field(ge=-1, le=1)
    """Normalised throttle action a_T in [-1, 1] as the policy outputs it."""
    a_steer: Finite = Field(ge=-1, le=1)
    """Normalised steering action a_delta in [-1, 1]."""
    throttle: Finite = Field(ge=0, le=1)
    """Physical throttle T = clip(a_T, 0, 1)."""
    steering_angle: Finite = Field(ge=-math.pi / 2, le=math.pi / 2)
    """Front wheel angle (rad), within the car's [delta_min, delta_max]."""
    scan_seq: int = Field(-1, ge=-1)
    scan_stamp_ns: int = Field(-1, ge=-1)
    compute_ns: int = Field(0, ge=0)


class VehicleState(Message):
    """Pose in the world frame and body-frame velocities (sim ground truth or odometry)."""

    TYPE: ClassVar[str] = "state"
    frame_id: str = "odom"
    source: Literal["sim", "real"]
    x: Finite
    y: Finite
    yaw: Finite
    vx: Finite = 0.0
    """Body-frame forward velocity (m/s)."""
    vy: Finite = 0.0
    """Body-frame lateral velocity (m/s), positive left."""
    yaw_rate: Finite = 0.0
    steering_angle: Finite = 0.0
    collided: bool = False


class Obstacle(BaseModel):
    """One obstacle car (ground truth)."""

    model_config = ConfigDict(extra="forbid")
    id: int
    x: Finite
    y: Finite
    yaw: Finite
    speed: Finite = 0.0
    length: Finite = Field(0.55, gt=0)
    width: Finite = Field(0.3, gt=0)


class ObstacleStates(Message):
    """Ground-truth obstacle cars, published by the simulator only (diagnosis, oracle baselines)."""

    TYPE: ClassVar[str] = "obstacles"
    frame_id: str = "odom"
    source: Literal["sim"] = "sim"
    obstacles: list[Obstacle] = Field(default_factory=list, max_length=256)


class ServiceStatus(Message):
    """Answer of racecav/<car>/<service>/status."""

    TYPE: ClassVar[str] = "status"
    service: str
    car: str
    pid: int = 0
    uptime_s: Finite = 0.0
    received: int = 0
    published: int = 0
    invalid: int = 0
    dropped: int = 0
    last_error: str = ""
    config_digest: str = ""
    info: dict[str, Any] = Field(default_factory=dict)
    """Service-specific state (mode, scenario, source, solver stats, ...), JSON-able."""
    outputs: dict[str, Any] = Field(default_factory=dict)
    """Latest published message per key, as JSON-able dicts."""


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls for cls in (Scan, DriveCommand, VehicleState, ObstacleStates, ServiceStatus)
}
