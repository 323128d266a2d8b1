"""ROS 2 messages of the bus: type names, RIHS01 type hashes, definitions and CDR conversion.

racecav message -> ROS 2 message (CDR, little-endian, as rmw and rosbag2 carry it):

| racecav        | ROS 2                                   | how                                          |
|----------------|-----------------------------------------|----------------------------------------------|
| Scan           | sensor_msgs/msg/LaserScan               | same fields (the Scan mirrors LaserScan)     |
| VehicleState   | nav_msgs/msg/Odometry                   | pose in ``odom``; twist (vx, vy, yaw_rate) in ``base_link`` |
| DriveCommand   | ackermann_msgs/msg/AckermannDriveStamped| steering_angle; speed = steady speed of throttle T |

and back: an AckermannDriveStamped from ROS ``/drive`` becomes a DriveCommand (source "ros"),
its speed turned into the throttle whose steady speed it is. Speed <-> throttle is the car
file's throttle model at the agent's speed scale (:func:`racecav.common.vehicle.steady_speed`),
the meaning the actuator's default throttle map gives T, so a speed means the same on both sides.

CDR comes from rosbags' typestore (its built-in ROS 2 Jazzy definitions need no download);
ackermann_msgs is not among them and is registered from its .msg text below. Field names and
types are all a RIHS01 hash covers, so the hashes equal those of a ROS installation (pinned in
tests/test_ros2_mirror.py).
"""

from __future__ import annotations

import math
import time
from functools import lru_cache

import numpy as np

from racecav.common.messages import DriveCommand, Scan, VehicleState
from racecav.common.vehicle import CarParams, steady_speed, throttle_for_speed

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
ACKERMANN_STAMPED = "ackermann_msgs/msg/AckermannDriveStamped"
ACKERMANN = "ackermann_msgs/msg/AckermannDrive"
TF = "tf2_msgs/msg/TFMessage"
TYPES = (LASER_SCAN, ODOMETRY, ACKERMANN_STAMPED)

HASH_UNSUPPORTED = "TypeHashNotSupported"
"""What rmw_zenoh on Humble puts where later distributions put the RIHS01 type hash."""

# ackermann_msgs (ros-drivers/ackermann_msgs, ROS 2 branch): fields only, comments dropped.
_ACKERMANN_MSG = """\
float32 steering_angle
float32 steering_angle_velocity
float32 speed
float32 acceleration
float32 jerk
"""
_ACKERMANN_STAMPED_MSG = """\
std_msgs/Header header
AckermannDrive drive
"""


@lru_cache(maxsize=1)
def typestore():
    """rosbags' ROS 2 Jazzy typestore with ackermann_msgs registered (built once per process)."""
    try:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError as e:  # the ros2 extra is optional
        raise ImportError("ROS 2 messages need the ros2 extra: pip install 'racecav[ros2]'") from e
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    types.update(get_types_from_msg(_ACKERMANN_MSG, ACKERMANN))
    types.update(get_types_from_msg(_ACKERMANN_STAMPED_MSG, ACKERMANN_STAMPED))
    ts.register(types)
    return ts


@lru_cache(maxsize=None)
def type_hash(name: str) -> str:
    """RIHS01 type hash of a ROS 2 type, e.g. ``RIHS01_64c1...`` for sensor_msgs/msg/LaserScan."""
    return typestore().hash_rihs01(name)


@lru_cache(maxsize=None)
def msgdef(name: str) -> str:
    """The type's .msg text with its dependencies (rosbag2's ``ros2msg`` schema encoding)."""
    return typestore().generate_msgdef(name, ros_version=2)[0]


def dds_type(name: str) -> str:
    """The type as rmw_zenoh spells it in keys: ``sensor_msgs::msg::dds_::LaserScan_``."""
    pkg, kind, typ = name.split("/")
    return f"{pkg}::{kind}::dds_::{typ}_"


def _time(stamp_ns: int):
    t = typestore().types["builtin_interfaces/msg/Time"]
    return t(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def _header(stamp_ns: int, frame_id: str):
    return typestore().types["std_msgs/msg/Header"](stamp=_time(stamp_ns), frame_id=frame_id)


def stamp_ns_of(header) -> int:
    """Nanoseconds of a ROS header's stamp."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class Converter:
    """racecav messages <-> ROS 2 CDR for one car.

    :param car: car parameters (throttle model for speed <-> throttle, steering limits).
    :param base_frame: the car's body frame (Odometry child_frame_id, AckermannDriveStamped frame).
    """

    def __init__(self, car: CarParams, base_frame: str = "base_link"):
        self.car, self.base_frame = car, base_frame
        ts = typestore()
        self._ts = ts
        self._T = ts.types
        self._cov = np.zeros(36, dtype=np.float64)

    def scan(self, scan: Scan, stamp_ns: int) -> bytes:
        """sensor_msgs/msg/LaserScan CDR of a Scan, stamped ``stamp_ns``."""
        msg = self._T[LASER_SCAN](
            header=_header(stamp_ns, scan.frame_id), angle_min=scan.angle_min, angle_max=scan.angle_max,
            angle_increment=scan.angle_increment, time_increment=scan.time_increment,
            scan_time=scan.scan_time, range_min=scan.range_min, range_max=scan.range_max,
            ranges=np.asarray(scan.ranges, dtype=np.float32),
            intensities=np.asarray(scan.intensities, dtype=np.float32))
        return bytes(self._ts.serialize_cdr(msg, LASER_SCAN))

    def odometry(self, state: VehicleState, stamp_ns: int) -> bytes:
        """nav_msgs/msg/Odometry CDR of a VehicleState (REP-105: pose in odom, twist in base)."""
        T = self._T
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=state.x, y=state.y, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(state.yaw / 2),
                                                         w=math.cos(state.yaw / 2)))
        twist = T["geometry_msgs/msg/Twist"](
            linear=T["geometry_msgs/msg/Vector3"](x=state.vx, y=state.vy, z=0.0),
            angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=state.yaw_rate))
        msg = T[ODOMETRY](
            header=_header(stamp_ns, state.frame_id), child_frame_id=self.base_frame,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=self._cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=self._cov))
        return bytes(self._ts.serialize_cdr(msg, ODOMETRY))

    def _transform(self, parent: str, child: str, x: float, y: float, z: float, yaw: float, stamp_ns: int):
        T = self._T
        return T["geometry_msgs/msg/TransformStamped"](
            header=_header(stamp_ns, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z)),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))))

    def tf(self, state: VehicleState, stamp_ns: int) -> bytes:
        """tf2_msgs/msg/TFMessage CDR: odom -> base_link at the state's pose (REP-105)."""
        t = self._transform(state.frame_id, self.base_frame, state.x, state.y, 0.0, state.yaw, stamp_ns)
        return bytes(self._ts.serialize_cdr(self._T[TF](transforms=[t]), TF))

    def tf_static(self, stamp_ns: int, laser_frame: str = "laser") -> bytes:
        """tf2_msgs/msg/TFMessage CDR: base_link -> laser, the car file's lidar mount."""
        m = self.car.lidar_mount
        t = self._transform(self.base_frame, laser_frame, m.x, m.y, m.z, m.yaw, stamp_ns)
        return bytes(self._ts.serialize_cdr(self._T[TF](transforms=[t]), TF))

    def speed(self, throttle: float) -> float:
        """Steady forward speed (m/s) of throttle T: the meaning of T on the car."""
        return float(steady_speed(throttle, self.car, self.car.agent_speed_scale))

    def drive(self, cmd: DriveCommand, stamp_ns: int) -> bytes:
        """ackermann_msgs/msg/AckermannDriveStamped CDR of a DriveCommand."""
        drive = self._T[ACKERMANN](steering_angle=cmd.steering_angle, steering_angle_velocity=0.0,
                                   speed=self.speed(cmd.throttle), acceleration=0.0, jerk=0.0)
        msg = self._T[ACKERMANN_STAMPED](header=_header(stamp_ns, self.base_frame), drive=drive)
        return bytes(self._ts.serialize_cdr(msg, ACKERMANN_STAMPED))

    def command_from_drive(self, data: bytes, seq: int, source: str = "ros") -> DriveCommand:
        """The DriveCommand of an AckermannDriveStamped from ROS (F1TENTH's ``/drive``).

        Speed becomes the throttle whose steady speed it is (no reverse: a negative speed is
        throttle 0, which brakes); the steering angle is clipped to the car's limits. Stamped
        with this host's monotonic clock (the stamp of the mux's other command inputs).

        :raises ValueError: for bytes that are not an AckermannDriveStamped or non-finite values,
            naming the field.
        """
        try:
            msg = self._ts.deserialize_cdr(data, ACKERMANN_STAMPED)
        except Exception as e:  # rosbags raises several types for short or garbled CDR
            raise ValueError(f"not an {ACKERMANN_STAMPED}: {type(e).__name__}: {e}") from None
        d = msg.drive
        for field in ("steering_angle", "speed"):
            if not math.isfinite(getattr(d, field)):
                raise ValueError(f"drive.{field}: not finite ({getattr(d, field)})")
        car = self.car
        steer = min(max(float(d.steering_angle), car.delta_min), car.delta_max)
        throttle = float(throttle_for_speed(max(float(d.speed), 0.0), car, car.agent_speed_scale))
        a_steer = min(max(steer / car.steer_gain, -1.0), 1.0)
        return DriveCommand(stamp_ns=time.monotonic_ns(), seq=seq, source=source, a_throttle=throttle,
                            a_steer=a_steer, throttle=throttle, steering_angle=steer)
