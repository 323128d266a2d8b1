"""Hostile payloads for the ROS 2 /drive input of ``racecav ros2`` (AckermannDriveStamped CDR, not
msgpack): the generator and the verdict shared by ``racecav bench faults`` and the fuzz test. The
racecav keys' payloads are common/fuzz.py's."""

from __future__ import annotations

import functools
import math
import struct

import numpy as np

from racecav.common import keys
from racecav.common.fuzz import random_payload
from racecav.services.ros2 import msgs

DRIVE_IN = "ros2:/drive"
"""Pseudo-leaf of the ROS /drive input of ``racecav ros2``: CDR on the ROS 2 data key the mirror
subscribes to (its status names the key), not a racecav key."""

F32_EXTREMES = [math.nan, math.inf, -math.inf, 3.4028235e38, -3.4028235e38, 1e-45, -0.0, 1e38, -1e38]


def drive_cdr(steer: float, speed: float, stamp_ns: int, frame: str = "base_link") -> bytes:
    """A valid ackermann_msgs/msg/AckermannDriveStamped (CDR), as a ROS node sends on /drive."""
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

    return msgs.Converter(load_car("slash"))


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
