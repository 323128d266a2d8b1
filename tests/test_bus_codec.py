"""Codec: round trips (property-based) and every kind of malformed payload is rejected."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from racecav.common.codec import SCHEMA_VERSION, DecodeError, decode, encode
from racecav.common.messages import (DriveCommand, Obstacle, ObstacleStates, Scan, ServiceStatus,
                                     VehicleState)

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
unit = st.floats(-1, 1, allow_nan=False)
stamps = st.integers(0, 2**63 - 1)


def scan(n=170, ranges=None, **kw) -> Scan:
    inc = (math.pi / 2) / (n - 1)
    r = np.full(n, 2.0, np.float32) if ranges is None else ranges
    return Scan(stamp_ns=1, seq=1, source="sim", angle_min=-math.pi / 4, angle_max=-math.pi / 4 + inc * (n - 1),
                angle_increment=inc, range_min=0.05, range_max=12.0, ranges=r, **kw)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(2, 400), seed=st.integers(0, 2**31), stamp=stamps, seq=st.integers(0, 2**40),
       with_inf=st.booleans())
def test_scan_round_trip(n, seed, stamp, seq, with_inf):
    r = np.random.default_rng(seed).uniform(0.05, 12, n).astype(np.float32)
    if with_inf:
        r[::7] = np.inf  # no return is +inf and must survive
    msg = scan(n, r).model_copy(update={"stamp_ns": stamp, "seq": seq})
    out = decode(encode(msg), Scan)
    assert out.stamp_ns == stamp and out.seq == seq
    np.testing.assert_array_equal(out.ranges, r)
    assert out.ranges.dtype == np.float32


@settings(max_examples=60, deadline=None)
@given(a_t=unit, a_s=unit, stamp=stamps, scan_seq=st.integers(-1, 2**40), src=st.text(min_size=1, max_size=64))
def test_command_round_trip(a_t, a_s, stamp, scan_seq, src):
    msg = DriveCommand(stamp_ns=stamp, source=src, a_throttle=a_t, a_steer=a_s, throttle=max(0.0, a_t),
                       steering_angle=0.3 * a_s, scan_seq=scan_seq, scan_stamp_ns=stamp)
    assert decode(encode(msg), DriveCommand) == msg


@settings(max_examples=30, deadline=None)
@given(x=finite, y=finite, yaw=finite, n=st.integers(0, 20))
def test_state_and_obstacles_round_trip(x, y, yaw, n):
    st_msg = VehicleState(stamp_ns=5, source="sim", x=x, y=y, yaw=yaw, vx=1.0)
    assert decode(encode(st_msg), VehicleState) == st_msg
    obs = ObstacleStates(stamp_ns=5, obstacles=[Obstacle(id=i, x=x, y=y, yaw=yaw) for i in range(n)])
    assert decode(encode(obs), ObstacleStates) == obs


def test_status_round_trip():
    msg = ServiceStatus(stamp_ns=1, service="policy", car="car0", received=3, info={"model": "reversed"},
                        outputs={"racecav/car0/cmd": {"throttle": 0.5}})
    assert decode(encode(msg), ServiceStatus) == msg


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2000))
def test_random_bytes_never_decode_to_garbage(data):
    try:
        msg = decode(data)
    except DecodeError as e:
        assert e.kind in {"msgpack", "version", "type", "schema", "oversize"}
    else:  # only a genuinely valid message may come out
        assert decode(encode(msg)) == msg


def _raw(msg) -> dict:
    return msgpack.unpackb(encode(msg), raw=False)


@pytest.mark.parametrize("mutate, kind", [
    (lambda d: d.update(v=SCHEMA_VERSION + 1), "version"),
    (lambda d: d.pop("v"), "version"),
    (lambda d: d.update(t="nope"), "type"),
    (lambda d: d.update(t="cmd"), "type"),
    (lambda d: d.update(angle_min="left"), "schema"),
    (lambda d: d.update(seq=-1), "schema"),
    (lambda d: d.update(ranges=d["ranges"][:-4]), "schema"),          # wrong array length
    (lambda d: d.update(ranges=d["ranges"][:-1]), "schema"),          # not a multiple of 4 bytes
    (lambda d: d.update(ranges=np.full(170, np.nan, "<f4").tobytes()), "schema"),  # NaN range
    (lambda d: d.update(angle_increment=float("nan")), "schema"),
    (lambda d: d.update(source="mars"), "schema"),
    (lambda d: d.update(extra_field=1), "schema"),
    (lambda d: d.pop("ranges"), "schema"),
])
def test_malformed_scan_rejected(mutate, kind):
    d = _raw(scan())
    mutate(d)
    with pytest.raises(DecodeError) as e:
        decode(msgpack.packb(d, use_bin_type=True), Scan)
    assert e.value.kind == kind


def test_oversize_and_non_map_rejected():
    with pytest.raises(DecodeError) as e:
        decode(b"\x00" * 70000)
    assert e.value.kind == "oversize"
    for data in (b"", b"\xc1", msgpack.packb([1, 2, 3]), msgpack.packb(3.5)):
        with pytest.raises(DecodeError) as e:
            decode(data)
        assert e.value.kind == "msgpack"


def test_command_out_of_range_rejected():
    d = _raw(DriveCommand(stamp_ns=1, source="policy", a_throttle=0.5, a_steer=0, throttle=0.5, steering_angle=0))
    d["a_throttle"] = 1.5
    with pytest.raises(DecodeError, match="a_throttle"):
        decode(msgpack.packb(d), DriveCommand)
