"""An independent CDR reader/writer for the tests: the ROS 2 messages re-declared as pycdr2 (the
IDL layer of Cyclone DDS) structs, field by field from the .msg files, so that what racecav's
rosbags-based code writes is checked by a different implementation."""


from dataclasses import dataclass

import pytest

pycdr2 = pytest.importorskip("pycdr2")
from pycdr2 import IdlStruct  # noqa: E402
from pycdr2.types import array, float32, float64, int32, sequence, uint32  # noqa: E402


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::Time"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::Header"):
    stamp: Time
    frame_id: str


@dataclass
class LaserScan(IdlStruct, typename="sensor_msgs::msg::LaserScan"):
    header: Header
    angle_min: float32
    angle_max: float32
    angle_increment: float32
    time_increment: float32
    scan_time: float32
    range_min: float32
    range_max: float32
    ranges: sequence[float32]
    intensities: sequence[float32]


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::Point"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::Quaternion"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::Pose"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::PoseWithCovariance"):
    pose: Pose
    covariance: array[float64, 36]


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::Vector3"):
    x: float64
    y: float64
    z: float64


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::Twist"):
    linear: Vector3
    angular: Vector3


@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs::msg::TwistWithCovariance"):
    twist: Twist
    covariance: array[float64, 36]


@dataclass
class Odometry(IdlStruct, typename="nav_msgs::msg::Odometry"):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance


@dataclass
class AckermannDrive(IdlStruct, typename="ackermann_msgs::msg::AckermannDrive"):
    steering_angle: float32
    steering_angle_velocity: float32
    speed: float32
    acceleration: float32
    jerk: float32


@dataclass
class AckermannDriveStamped(IdlStruct, typename="ackermann_msgs::msg::AckermannDriveStamped"):
    header: Header
    drive: AckermannDrive


BY_TYPE = {
    "sensor_msgs/msg/LaserScan": LaserScan,
    "nav_msgs/msg/Odometry": Odometry,
    "ackermann_msgs/msg/AckermannDriveStamped": AckermannDriveStamped,
}


def stamp_ns(h) -> int:
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def drive_cdr(steering_angle: float, speed: float, stamp: int = 0, frame: str = "base_link") -> bytes:
    """An AckermannDriveStamped as a ROS node would send it (encapsulation header 00 01 00 00)."""
    msg = AckermannDriveStamped(Header(Time(stamp // 1_000_000_000, stamp % 1_000_000_000), frame),
                                AckermannDrive(steering_angle, 0.0, speed, 0.0, 0.0))
    return msg.serialize()
