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
