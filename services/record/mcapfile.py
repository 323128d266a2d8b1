"""The run file: one MCAP holding a run's raw bus samples and ROS 2 copies of them.

Channels (MCAP profile ``ros2``, so rosbag2, rosbags and Foxglove open the file):

- one per recorded Zenoh key, topic = the key (``racecav/car0/scan``): the bus payload byte for
  byte (exact replay) wrapped in a ``racecav_msgs/msg/RawSample`` (``uint8[] payload``; message
  encoding ``cdr``, its ``ros2msg`` schema in the file), so ROS tools and Foxglove decode every
  channel (MCAP registers no msgpack encoding: a custom one is flagged as unsupported); the
  message type and wire schema version in the channel metadata (``racecav_type``,
  ``racecav_schema_version``);
- ROS 2 copies: ``/scan`` sensor_msgs/msg/LaserScan, ``/odom`` nav_msgs/msg/Odometry,
  ``/drive`` ackermann_msgs/msg/AckermannDriveStamped (the controller's command, F1TENTH's
  name), and the frame tree: ``/tf`` tf2_msgs/msg/TFMessage odom -> base_link (one per vehicle
  state) and ``/tf_static`` base_link -> laser (the car file's lidar mount, once per file, at its
  first message), so Foxglove's 3D panel places the scan in ``odom``; message encoding ``cdr``,
  schema encoding ``ros2msg`` (the .msg text with its dependencies), ``offered_qos_profiles`` and
  ``topic_type_hash`` metadata, as rosbag2's MCAP storage writes them.

Log time is what the recorder passes: the sample's own stamp (``racecav record``: sim time in
the simulator, this host's monotonic clock on the car), so a run plays back at its own speed;
header stamps of the ROS copies are the messages' stamps. A metadata record ``racecav`` names the
car and the configuration digest. A file that got no message is removed when it is closed.
"""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass
from pathlib import Path

import msgpack

from racecav.common import keys
from racecav.common.codec import SCHEMA_VERSION, DecodeError, decode
from racecav.common.messages import MESSAGE_TYPES, DriveCommand, Scan, VehicleState

RAW_SCHEMA = "racecav_msgs/msg/RawSample"
RAW_MSGDEF = "uint8[] payload\n"
"""The raw sample's ROS 2 type: the bus payload (msgpack, racecav.common.codec) as bytes; the key
is the channel's topic."""
LEGACY_RAW_ENCODING = "racecav-msgpack"
"""Files written before RawSample kept the payload as it is under this custom encoding (read only)."""
_CDR_LE = b"\x00\x01\x00\x00"
PROFILE = "ros2"

ROS_COPIES: dict[str, tuple[str, str]] = {
    keys.SCAN: ("/scan", "sensor_msgs/msg/LaserScan"),
    keys.STATE: ("/odom", "nav_msgs/msg/Odometry"),
    keys.CMD: ("/drive", "ackermann_msgs/msg/AckermannDriveStamped"),
}
"""Bus leaf -> (ROS 2 topic, type) of the CDR copies."""
TF_TYPE = "tf2_msgs/msg/TFMessage"
_ROS_TIME_MAX_NS = 2**31 * 1_000_000_000
_LEAF_CLASS = {keys.SCAN: Scan, keys.STATE: VehicleState, keys.CMD: DriveCommand}


def _qos(durability: int) -> str:
    """rosbag2's YAML (bag version <= 8: integer enums) for one offered QoS profile: reliable,
    keep_last 10, the given durability (1 transient_local, 2 volatile), defaults else."""
    return ("- history: 1\n  depth: 10\n  reliability: 1\n  durability: %d\n"
            "  deadline:\n    sec: 9223372036\n    nsec: 854775807\n"
            "  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n"
            "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n"
            "  avoid_ros_namespace_conventions: false\n" % durability)


_QOS = _qos(2)
_QOS_LATCHED = _qos(1)  # /tf_static: transient local, as tf2's static broadcaster offers it


def raw_cdr(payload: bytes) -> bytes:
    """A RawSample's CDR: encapsulation header, uint32 length, the bytes."""
    return _CDR_LE + struct.pack("<I", len(payload)) + payload


def raw_payload(data: bytes) -> bytes:
    """The bus payload of a RawSample's CDR; ValueError if it is not one."""
    if len(data) < 8 or data[:2] != _CDR_LE[:2]:
        raise ValueError("not a little-endian CDR RawSample")
    (n,) = struct.unpack_from("<I", data, 4)
    if 8 + n > len(data):
        raise ValueError(f"RawSample of {n} bytes in {len(data) - 8}")
    return bytes(data[8:8 + n])


def stamp_of(payload: bytes) -> int | None:
    """The ``stamp_ns`` of a racecav message payload (0 <= stamp < 2^63), or None (an untyped key
    such as the e-stop, garbage)."""
    try:
        d = msgpack.unpackb(payload, raw=False)
    except Exception:  # not msgpack
        return None
    t = d.get("stamp_ns") if isinstance(d, dict) else None
    return t if type(t) is int and 0 <= t < 2**63 else None


class RunFileError(Exception):
    """A run file that is missing, not MCAP, or not a racecav run; the message names the file."""


def _mcap():
    try:
        import mcap.writer  # noqa: F401
        import mcap.reader  # noqa: F401
    except ImportError as e:
        raise ImportError("run files need the record extra: pip install 'racecav[record]'") from e
    return mcap


def _type_of(payload: bytes) -> str | None:
    """The racecav message type named in a payload ("scan", "cmd"...), or None."""
    try:
        d = msgpack.unpackb(payload, raw=False)
    except Exception:  # not msgpack: an untyped key (e-stop) or garbage
        return None
    t = d.get("t") if isinstance(d, dict) else None
    return t if t in MESSAGE_TYPES else None


class RunWriter:
    """Writes a run file. Not thread-safe: one thread calls :meth:`write` (the recorder's loop).

    :param path: output .mcap path (parent folders are created).
    :param car: the car name (keys racecav/<car>/...).
    :param ros: also write the ROS 2 CDR copies and the frame tree (needs rosbags).
    :param car_params: car file name: the ROS copies' speed <-> throttle mapping, the lidar mount.
    :param metadata: extra strings for the ``racecav`` metadata record.
    :param follow_symlinks: False: refuse a path whose last component is a symlink (O_NOFOLLOW).
    """

    def __init__(self, path: str | Path, car: str, ros: bool = True, car_params: str = "slash",
                 metadata: dict[str, str] | None = None, follow_symlinks: bool = True):
        _mcap()
        from mcap.writer import Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.car = car
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | (0 if follow_symlinks else os.O_NOFOLLOW)
        self._file = os.fdopen(os.open(self.path, flags, 0o644), "wb")
        self._w = Writer(self._file)
        self._w.start(profile=PROFILE, library="racecav")
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self.counts: dict[str, int] = {}
        self.messages = 0
        self.bytes = 0
        self.first_log_time: int | None = None
        self.last_log_time: int | None = None
        self._meta = {"car": car, "started_unix_ns": str(time.time_ns()), **(metadata or {})}
        self._conv = None
        self._convert = {}
        if ros:
            from racecav.common.vehicle import load_car
            from racecav.services.ros2.msgs import Converter

            self._conv = Converter(load_car(car_params))
            self._convert = {keys.SCAN: self._conv.scan, keys.STATE: self._conv.odometry,
                             keys.CMD: self._conv.drive}

    def _channel(self, topic: str, encoding: str, schema_name: str, schema_enc: str, schema: bytes,
                 metadata: dict[str, str]) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._w.register_schema(name=schema_name, encoding=schema_enc, data=schema) if schema_name else 0
            cid = self._w.register_channel(topic=topic, message_encoding=encoding, schema_id=sid,
                                           metadata=metadata)
            self._channels[topic] = cid
            self._seq[cid] = 0
        return cid

    def _ros_channel(self, topic: str, type_name: str, qos: str = _QOS) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            from racecav.services.ros2.msgs import msgdef, type_hash

            cid = self._channel(topic, "cdr", type_name, "ros2msg", msgdef(type_name).encode(),
                                {"offered_qos_profiles": qos, "topic_type_hash": type_hash(type_name)})
        return cid

    def _add(self, cid: int, topic: str, data: bytes, log_time: int) -> None:
        self._seq[cid] += 1
        self._w.add_message(channel_id=cid, log_time=log_time, data=data, publish_time=log_time,
                            sequence=self._seq[cid])
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.messages += 1
        self.bytes += len(data)
        if self.first_log_time is None:
            self.first_log_time = log_time
        self.last_log_time = log_time

    def write(self, key: str, payload: bytes, log_time_ns: int | None = None) -> None:
        """Record one bus sample (and its ROS copies if it has them and decodes) at ``log_time_ns``
        (default: now on this host's real-time clock)."""
        t = time.time_ns() if log_time_ns is None else log_time_ns
        if self._conv is not None and self.messages == 0:  # the frame tree's fixed part, first
            self._add(self._ros_channel("/tf_static", TF_TYPE, _QOS_LATCHED), "/tf_static", self._conv.tf_static(t if 0 <= t < _ROS_TIME_MAX_NS else 0), t)
        cid = self._channels.get(key)
        if cid is None:
            typ = _type_of(payload)
            cid = self._channel(key, "cdr", RAW_SCHEMA, "ros2msg", RAW_MSGDEF.encode(),
                                {"racecav_type": typ or "", "racecav_schema_version": str(SCHEMA_VERSION)})
        self._add(cid, key, raw_cdr(payload), t)
        leaf = key.rsplit("/", 1)[-1]
        if self._conv is None or leaf not in self._convert or key != keys.topic(self.car, leaf):
            return
        topic, type_name = ROS_COPIES[leaf]
        try:
            msg = decode(payload, _LEAF_CLASS[leaf])
        except DecodeError:
            return  # kept raw (as received), no ROS copy of an invalid message
        if not 0 <= msg.stamp_ns < _ROS_TIME_MAX_NS:
            return  # a stamp builtin_interfaces/Time (int32 seconds) cannot hold: kept raw only
        self._add(self._ros_channel(topic, type_name), topic, self._convert[leaf](msg, msg.stamp_ns), t)
        if leaf == keys.STATE:
            self._add(self._ros_channel("/tf", TF_TYPE), "/tf", self._conv.tf(msg, msg.stamp_ns), t)

    def close(self) -> None:
        """Write the metadata record and the summary; the file is complete only after this. A
        file that got no message is removed (an empty run is no run)."""
        if self._file.closed:
            return
        self._w.add_metadata("racecav", {k: str(v) for k, v in self._meta.items()})
        # rosbag2's MCAP storage reads the QoS YAML by the bag version of this record; an empty
        # serialized_metadata means version 8, whose integer QoS enums _QOS uses (Humble to Jazzy).
        self._w.add_metadata("rosbag2", {"serialized_metadata": ""})
        self._w.finish()
        self._file.close()
        if self.messages == 0:
            self.path.unlink(missing_ok=True)


@dataclass
class RawSample:
    key: str
    log_time_ns: int
    payload: bytes


def read_raw(path: str | Path, key_filter=None) -> list[RawSample]:
    """Every raw bus sample of a run file, in log-time order.

    :param key_filter: a predicate on the key, or None for all.
    :raises RunFileError: naming the file when it is missing, not MCAP, truncated or has no raw
        racecav channels.
    """
    _mcap()
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    p = Path(path)
    if not p.is_file():
        raise RunFileError(f"{p}: no such file")
    out: list[RawSample] = []
    try:
        with open(p, "rb") as f:
            reader = make_reader(f)
            header = reader.get_header()
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                if schema is not None and schema.name == RAW_SCHEMA:
                    data = raw_payload(message.data)
                elif channel.message_encoding == LEGACY_RAW_ENCODING:
                    data = bytes(message.data)
                else:
                    continue
                if key_filter is None or key_filter(channel.topic):
                    out.append(RawSample(channel.topic, message.log_time, data))
    except (McapError, ValueError, EOFError, OSError, KeyError, IndexError) as e:
        raise RunFileError(f"{p}: not a readable MCAP run file ({type(e).__name__}: {e})") from None
    except Exception as e:  # the mcap reader raises assorted errors on garbage
        raise RunFileError(f"{p}: not a readable MCAP run file ({type(e).__name__}: {e})") from None
    if header.profile != PROFILE and not out:
        raise RunFileError(f"{p}: MCAP file without racecav channels (profile {header.profile!r})")
    return out


def run_cars(samples: list[RawSample]) -> list[str]:
    """Cars that have a scan channel in the samples."""
    return sorted({s.key.split("/")[1] for s in samples
                   if s.key.startswith(keys.PREFIX + "/") and s.key.endswith("/" + keys.SCAN)})
