"""The run file: one MCAP holding a run's raw bus samples and ROS 2 copies of them.

Channels (MCAP profile ``ros2``, so rosbag2, rosbags and Foxglove open the file):

- one per recorded Zenoh key, topic = the key (``racecav/car0/scan``), message encoding
  ``racecav-msgpack`` (the bus payload byte for byte: exact replay; MCAP registers no msgpack
  encoding, hence a custom name), a schema record named ``racecav/<type>`` with no schema in it
  (empty encoding: rosbag2 needs a schema record per channel and reads only ROS schema encodings),
  the message type and wire schema version in the channel metadata (``racecav_type``,
  ``racecav_schema_version``);
- ROS 2 copies: ``/scan`` sensor_msgs/msg/LaserScan, ``/odom`` nav_msgs/msg/Odometry and
  ``/drive`` ackermann_msgs/msg/AckermannDriveStamped (the controller's command, F1TENTH's
  name), message encoding ``cdr``, schema encoding ``ros2msg`` (the .msg text with its
  dependencies), ``offered_qos_profiles`` and ``topic_type_hash`` metadata, as rosbag2's MCAP
  storage writes them.

Log time is the arrival time on this host's real-time clock; header stamps of the ROS copies are
the same (the racecav stamp, which may be sim time, stays in the raw sample). A metadata record
``racecav`` names the car and the configuration digest.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import msgpack

from racecav.common import keys
from racecav.common.codec import SCHEMA_VERSION, DecodeError, decode
from racecav.common.messages import MESSAGE_TYPES, DriveCommand, Scan, VehicleState

RAW_ENCODING = "racecav-msgpack"
PROFILE = "ros2"

ROS_COPIES: dict[str, tuple[str, str]] = {
    keys.SCAN: ("/scan", "sensor_msgs/msg/LaserScan"),
    keys.STATE: ("/odom", "nav_msgs/msg/Odometry"),
    keys.CMD: ("/drive", "ackermann_msgs/msg/AckermannDriveStamped"),
}
"""Bus leaf -> (ROS 2 topic, type) of the CDR copies."""
_LEAF_CLASS = {keys.SCAN: Scan, keys.STATE: VehicleState, keys.CMD: DriveCommand}

# rosbag2's YAML (bag version <= 8: integer enums) for one offered QoS profile: reliable,
# volatile, keep_last 10, defaults else.
_QOS = ("- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n"
        "  deadline:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  avoid_ros_namespace_conventions: false\n")


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
    :param ros: also write the ROS 2 CDR copies (needs rosbags).
    :param car_params: car file name for the ROS copies' speed <-> throttle mapping.
    :param metadata: extra strings for the ``racecav`` metadata record.
    """

    def __init__(self, path: str | Path, car: str, ros: bool = True, car_params: str = "slash",
                 metadata: dict[str, str] | None = None):
        _mcap()
        from mcap.writer import Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.car = car
        self._file = open(self.path, "wb")
        self._w = Writer(self._file)
        self._w.start(profile=PROFILE, library="racecav")
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self.counts: dict[str, int] = {}
        self.bytes = 0
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

    def _add(self, cid: int, topic: str, data: bytes, log_time: int) -> None:
        self._seq[cid] += 1
        self._w.add_message(channel_id=cid, log_time=log_time, data=data, publish_time=log_time,
                            sequence=self._seq[cid])
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.bytes += len(data)

    def write(self, key: str, payload: bytes, log_time_ns: int | None = None) -> None:
        """Record one bus sample (and its ROS copy if it has one and decodes)."""
        t = time.time_ns() if log_time_ns is None else log_time_ns
        cid = self._channels.get(key)
        if cid is None:
            typ = _type_of(payload)
            # A schema record without a schema (empty encoding, as MCAP allows): rosbag2 refuses a
            # channel that has no schema record at all (`ros2 bag info`: "Could not find schema").
            cid = self._channel(key, RAW_ENCODING, f"racecav/{typ or 'bytes'}", "", b"",
                                {"racecav_type": typ or "", "racecav_schema_version": str(SCHEMA_VERSION)})
        self._add(cid, key, payload, t)
        leaf = key.rsplit("/", 1)[-1]
        if self._conv is None or leaf not in self._convert or key != keys.topic(self.car, leaf):
            return
        from racecav.services.ros2.msgs import msgdef, type_hash

        topic, type_name = ROS_COPIES[leaf]
        try:
            msg = decode(payload, _LEAF_CLASS[leaf])
        except DecodeError:
            return  # kept raw (as received), no ROS copy of an invalid message
        rid = self._channels.get(topic)
        if rid is None:
            rid = self._channel(topic, "cdr", type_name, "ros2msg", msgdef(type_name).encode(),
                                {"offered_qos_profiles": _QOS, "topic_type_hash": type_hash(type_name)})
        self._add(rid, topic, self._convert[leaf](msg, t), t)

    def close(self) -> None:
        """Write the metadata record and the summary; the file is complete only after this."""
        if self._file.closed:
            return
        self._w.add_metadata("racecav", {k: str(v) for k, v in self._meta.items()})
        # rosbag2's MCAP storage reads the QoS YAML by the bag version of this record; an empty
        # serialized_metadata means version 8, whose integer QoS enums _QOS uses (Humble to Jazzy).
        self._w.add_metadata("rosbag2", {"serialized_metadata": ""})
        self._w.finish()
        self._file.close()


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
            for _schema, channel, message in reader.iter_messages(log_time_order=True):
                if channel.message_encoding != RAW_ENCODING:
                    continue
                if key_filter is None or key_filter(channel.topic):
                    out.append(RawSample(channel.topic, message.log_time, bytes(message.data)))
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
