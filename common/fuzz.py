"""Hostile payloads for every input key of the services: the fuzz test and ``racecav bench faults``.

Each key gets a mix of: random bytes, truncated or bit-flipped valid payloads, msgpack values that
are not maps, maps of the wrong message type, and valid messages with one field replaced by an
extreme or wrongly typed value (2^64-1, -2^63, +-1e308, 5e-324, inf, NaN, strings, booleans,
maps, lists, huge strings). Whether a payload is valid is decided by the codec itself
(:func:`expected_invalid`), so the counts a service must report are known exactly.

Two generators share the same pieces: a numpy RNG one (fast: the bench sends >= 10,000 per key)
and hypothesis strategies (the tests: shrinking, reproducible failures).
"""

from __future__ import annotations

import functools
import json
import math
import struct

import msgpack
import numpy as np

from racecav.common import keys
from racecav.common.codec import DecodeError, decode, encode
from racecav.common.messages import DriveCommand, Message, Obstacle, ObstacleStates, Scan, VehicleState

EXTREMES: list = [2**64 - 1, 2**63, 2**63 - 1, -2**63, -1, 0, 1e308, -1e308, 5e-324, math.inf, -math.inf,
                  math.nan, "1.0", "", "x" * 5000, True, False, None, {}, {"a": 1}, [], [1.0, 2.0],
                  b"\x00\x01\x02", b"\xff" * 7]
"""Values swapped into one field of a valid message."""

COMMAND_SOURCES = {keys.CMD: "policy", keys.TELEOP: "teleop", keys.SAFETY: "safety", keys.DRIVE_ROS: "ros"}

INPUTS: dict[str, type[Message] | None] = {
    keys.SCAN: Scan, keys.CMD: DriveCommand, keys.TELEOP: DriveCommand, keys.SAFETY: DriveCommand,
    keys.DRIVE_ROS: DriveCommand, keys.STATE: VehicleState, keys.OBSTACLES: ObstacleStates,
    keys.ESTOP: None, "safety/verdict": None,
}
"""Every input key leaf (racecav/<car>/<leaf>) some service subscribes to, and its message class
(None: raw bytes, e.g. the e-stop)."""


@functools.lru_cache(maxsize=1)
def _lidar():
    from racecav.common.vehicle import load_car

    return load_car("slash").lidar


def valid_message(leaf: str, rng: np.random.Generator) -> Message | bytes:
    """A valid message for ``leaf`` (raw keys: a valid raw payload)."""
    cls = INPUTS[leaf]
    if cls is Scan:
        from racecav.common.lidar import make_scan

        spec = _lidar()
        ranges = rng.uniform(0.2, 12.0, spec.n_rays).astype(np.float32)
        return make_scan(ranges, int(rng.integers(0, 2**40)), int(rng.integers(0, 2**20)), "sim", spec)
    if cls is DriveCommand:
        a_t, a_s = (float(x) for x in rng.uniform(-1, 1, 2))
        return DriveCommand(stamp_ns=int(rng.integers(0, 2**40)), seq=int(rng.integers(0, 1000)),
                            source=COMMAND_SOURCES[leaf], a_throttle=a_t, a_steer=a_s,
                            throttle=min(max(a_t, 0.0), 1.0), steering_angle=0.36 * a_s)
    if cls is VehicleState:
        x, y, yaw = (float(v) for v in rng.uniform(-3, 3, 3))
        return VehicleState(stamp_ns=1, source="sim", x=x, y=y, yaw=yaw, vx=1.0)
    if cls is ObstacleStates:
        return ObstacleStates(stamp_ns=1, obstacles=[Obstacle(id=i, x=float(i), y=0.0, yaw=0.0) for i in range(3)])
    if leaf == "safety/verdict":
        return json.dumps({"scan_seq": int(rng.integers(0, 1000)), "brake": False, "ttc_s": 9.0, "v": 1.0}).encode()
    return b"stop"


def _as_bytes(msg: Message | bytes) -> bytes:
    return msg if isinstance(msg, bytes) else encode(msg)


def mutate_field(msg: Message, field: str, value) -> bytes:
    """``msg`` with ``field`` set to ``value``, packed (whatever msgpack can carry)."""
    d = msgpack.unpackb(encode(msg), raw=False)
    d[field] = value
    try:
        return msgpack.packb(d, use_bin_type=True)
    except (OverflowError, TypeError, ValueError):  # beyond msgpack itself: send the bytes as a string
        d[field] = repr(value)[:100]
        return msgpack.packb(d, use_bin_type=True)


def random_payload(leaf: str, rng: np.random.Generator) -> bytes:
    """One hostile (or, rarely, valid) payload for ``leaf``."""
    base = valid_message(leaf, rng)
    kind = int(rng.integers(0, 8))
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 200)))
    raw = _as_bytes(base)
    if kind == 1:
        return raw[: int(rng.integers(0, len(raw) + 1))]
    if kind == 2:
        b = bytearray(raw)
        for _ in range(int(rng.integers(1, 4))):
            b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
        return bytes(b)
    if kind == 3:
        return msgpack.packb(EXTREMES[int(rng.integers(0, len(EXTREMES)))], use_bin_type=True)
    if kind == 4:  # another type's message
        other = [k for k in INPUTS if INPUTS[k] is not None and INPUTS[k] is not INPUTS[leaf]]
        return _as_bytes(valid_message(other[int(rng.integers(0, len(other)))], rng))
    if kind == 5 or isinstance(base, bytes):
        return raw
    fields = list(type(base).model_fields)
    field = fields[int(rng.integers(0, len(fields)))]
    return mutate_field(base, field, EXTREMES[int(rng.integers(0, len(EXTREMES)))])


def expected_invalid(leaf: str, payload: bytes, max_bytes: int = 65536) -> bool:
    """True if a service decoding ``leaf`` must reject ``payload`` (counted as invalid)."""
    cls = INPUTS[leaf]
    if cls is None:
        return False
    try:
        decode(payload, cls, max_bytes)
    except DecodeError:
        return True
    return False


# --- the ROS 2 /drive input of ``racecav ros2`` (AckermannDriveStamped CDR, not msgpack) ----------

DRIVE_IN = "ros2:/drive"
"""Pseudo-leaf of the ROS /drive input of ``racecav ros2``: CDR on the ROS 2 data key the mirror
subscribes to (its status names the key), not a racecav key."""

F32_EXTREMES = [math.nan, math.inf, -math.inf, 3.4028235e38, -3.4028235e38, 1e-45, -0.0, 1e38, -1e38]


def drive_cdr(steer: float, speed: float, stamp_ns: int, frame: str = "base_link") -> bytes:
    """A valid ackermann_msgs/msg/AckermannDriveStamped (CDR), as a ROS node sends on /drive."""
    from racecav.services.ros2 import msgs

    ts = msgs.typestore()
    drive = ts.types[msgs.ACKERMANN](steering_angle=steer, steering_angle_velocity=0.0, speed=speed,
                                     acceleration=0.0, jerk=0.0)
    msg = ts.types[msgs.ACKERMANN_STAMPED](header=msgs._header(stamp_ns, frame), drive=drive)
    return bytes(ts.serialize_cdr(msg, msgs.ACKERMANN_STAMPED))


def flip_bits(raw: bytes, bits: list[int]) -> bytes:
    b = bytearray(raw)
    for x in bits:
        b[(x >> 3) % len(b)] ^= 1 << (x & 7)
    return bytes(b)


def set_drive_float(raw: bytes, i: int, value: float | int) -> bytes:
    """Field ``i`` of the five float32 of AckermannDrive (the last 20 bytes: 4-aligned, last)
    set to ``value`` (an int: raw bits)."""
    off = len(raw) - 20 + 4 * i
    packed = struct.pack("<I", value) if isinstance(value, int) else struct.pack("<f", value)
    return raw[:off] + packed + raw[off + 4:]


def random_drive_payload(rng: np.random.Generator, max_bytes: int = 1024) -> bytes:
    """One hostile (or valid) payload for the ROS /drive key: random bytes, valid CDR, truncated
    and bit-flipped CDR, extreme float32 values, a forged frame_id length, racecav msgpack on the
    ROS key, and payloads over ``ros2.max_payload_bytes`` (valid CDR with a long frame_id)."""
    valid = drive_cdr(float(rng.uniform(-1, 1)), float(rng.uniform(-20, 20)), int(rng.integers(0, 2**31 * 10**9)),
                      "base_link" if rng.random() < 0.7 else "f" * int(rng.integers(0, 40)))
    kind = int(rng.integers(0, 8))
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 300)))
    if kind == 1:
        return valid[: int(rng.integers(0, len(valid) + 1))]
    if kind == 2:
        return flip_bits(valid, [int(x) for x in rng.integers(0, 2**20, int(rng.integers(1, 4)))])
    if kind == 3:
        v = F32_EXTREMES[int(rng.integers(0, len(F32_EXTREMES)))] if rng.random() < 0.5 else int(rng.integers(0, 2**32))
        return set_drive_float(valid, int(rng.integers(0, 5)), v)
    if kind == 4:  # a forged frame_id length
        return valid[:12] + struct.pack("<I", int(rng.integers(0, 2**32))) + valid[16:]
    if kind == 5:
        return random_payload(keys.DRIVE_ROS, rng)
    if kind == 6:  # over the size limit, otherwise valid
        return drive_cdr(0.0, 1.0, 1, "x" * int(rng.integers(max_bytes, 4 * max_bytes)))
    return valid


@functools.lru_cache(maxsize=1)
def _drive_converter():
    from racecav.common.vehicle import load_car
    from racecav.services.ros2.msgs import Converter

    return Converter(load_car("slash"))


def drive_invalid(payload: bytes, max_bytes: int = 1024) -> bool:
    """True if the mirror must refuse ``payload`` on /drive: over ``ros2.max_payload_bytes`` or
    refused by its CDR converter."""
    if len(payload) > max_bytes:
        return True
    try:
        _drive_converter().command_from_drive(payload, 0)
    except ValueError:
        return True
    return False


def strategy(leaf: str):
    """Hypothesis strategy of hostile payloads for ``leaf`` (imported only by tests)."""
    from hypothesis import strategies as st

    extremes = st.one_of(st.sampled_from(EXTREMES), st.integers(-2**63, 2**64 - 1), st.floats(),
                         st.text(max_size=20), st.binary(max_size=20))
    seeds = st.integers(0, 2**32 - 1)
    base = seeds.map(lambda s: valid_message(leaf, np.random.default_rng(s)))
    parts = [st.binary(max_size=300), seeds.map(lambda s: random_payload(leaf, np.random.default_rng(s)))]
    if INPUTS[leaf] is not None:
        fields = list(INPUTS[leaf].model_fields)
        parts.append(st.tuples(base, st.sampled_from(fields), extremes).map(lambda t: mutate_field(*t)))
    return st.one_of(*parts)


QUERIES: dict[str, list] = {
    "reset": [{"seed": 2**70}, {"seed": -1}, {"seed": True}, {"seed": 1.5}, {"seed": "1"}, {"heading": "up"},
              {"nope": 1}, [], "x", None, 1e308],
    "scenario": [{"name": "/etc/passwd"}, {"name": "../../etc/passwd"}, {"name": ""}, {"name": "x" * 1000},
                 {"name": "head-to-head", "seed": 2**64}, {"name": 3}, {}, [1], "racetrack"],
}
"""Bad payloads for the sim's queryables (valid ones are sent separately)."""

BAD_QUERY_BYTES = [b"\xff\xfe", b"{", b"\x00" * 100, b"[" * 5000, json.dumps({"seed": 10**400}).encode()]
