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
@given(x=finite, y=finite, yaw=st.floats(-4 * math.pi, 4 * math.pi), n=st.integers(0, 20))
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


# --- hardening (issue 19): every reported killer payload is a DecodeError, nothing else ---------

INT64_MAX = 2**63 - 1


@pytest.mark.parametrize("field, value", [
    ("stamp_ns", 2**64 - 1),               # passed decoding, then overflowed stamp + compute_ns
    ("stamp_ns", 2**63),
    ("seq", 2**63),
    ("angle_min", -1e308),                 # OverflowError from round(inf)
    ("angle_max", 1e308),
    ("angle_increment", 5e-324),
    ("angle_increment", 1e-9),
    ("ranges", {"a": 1}),                  # TypeError in the array validator
    ("intensities", {"a": 1}),
    ("angle_min", "-0.78"),                # strings are not coerced
    ("range_max", True),                   # nor booleans
    ("stamp_ns", 1.5),
    ("stamp_ns", True),
    ("frame_id", 7),
    ("frame_id", "x" * 65),
    ("ranges", np.full(170, -1.0, "<f4").tobytes()),
    ("scan_time", 1e300),
])
def test_scan_extremes_only_decode_error(field, value):
    d = _raw(scan())
    d[field] = value
    with pytest.raises(DecodeError) as e:
        decode(msgpack.packb(d, use_bin_type=True), Scan)
    assert e.value.kind == "schema"


def _cmd(**kw) -> dict:
    base = dict(stamp_ns=1, source="policy", a_throttle=0.5, a_steer=0.5, throttle=0.5, steering_angle=0.18)
    return _raw(DriveCommand(**{**base, **kw}))


@pytest.mark.parametrize("field, value", [
    ("a_throttle", -1.0),       # contradicts throttle 0.5
    ("throttle", 1.0),          # contradicts a_throttle 0.5
    ("steering_angle", -0.18),  # opposite sign of a_steer
    ("throttle", "1"),
    ("a_steer", True),
    ("compute_ns", 2**63),
    ("scan_stamp_ns", 2**64 - 1),
    ("source", ""),
    ("source", b"policy"),
    ("brake", True),            # braking with throttle 0.5
    ("brake", 1),
])
def test_command_inconsistent_or_coerced_rejected(field, value):
    d = _cmd()
    d[field] = value
    with pytest.raises(DecodeError) as e:
        decode(msgpack.packb(d, use_bin_type=True), DriveCommand)
    assert e.value.kind == "schema" and field in str(e.value)


def test_command_consistent_accepted():
    for a_t, t in ((-1.0, 0.0), (0.3, 0.3), (1.0, 1.0)):
        out = decode(msgpack.packb(_cmd(a_throttle=a_t, throttle=t)), DriveCommand)
        assert out.throttle == t
    assert decode(msgpack.packb(_cmd(a_steer=0.0, steering_angle=0.0)), DriveCommand).a_steer == 0.0
    assert decode(msgpack.packb(_cmd(a_throttle=-0.9, throttle=0.0, brake=True)), DriveCommand).brake
    old = _cmd()  # a producer that predates the field: not braking
    del old["brake"]
    assert decode(msgpack.packb(old), DriveCommand).brake is False


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.sampled_from(["stamp_ns", "seq", "angle_min", "angle_max", "angle_increment",
                                        "ranges", "intensities", "range_min", "range_max", "source",
                                        "frame_id", "time_increment", "scan_time"]),
                       st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(),
                                 st.text(max_size=8), st.binary(max_size=64),
                                 st.lists(st.floats(), max_size=4),
                                 st.dictionaries(st.text(max_size=3), st.integers(-2**63, 2**63 - 1), max_size=2))))
def test_scan_field_fuzz_only_decode_error(over):
    d = _raw(scan())
    d.update(over)
    try:
        msg = decode(msgpack.packb(d, use_bin_type=True), Scan)
    except DecodeError:
        return
    assert 0 <= msg.stamp_ns <= INT64_MAX and math.isfinite(msg.angle_min) and msg.angle_increment >= 1e-5
    again = decode(encode(msg), Scan)  # whatever is accepted survives a round trip
    assert again.stamp_ns == msg.stamp_ns and np.array_equal(again.ranges, msg.ranges)
