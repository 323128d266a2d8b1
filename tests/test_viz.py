"""``racecav viz``: a WebSocket client (the Foxglove WebSocket protocol, subprotocol foxglove.sdk.v1)
subscribes to every channel the server advertises and checks a message of each against what was
published on the bus; ``--mcap`` writes the same channels to a file."""

from __future__ import annotations

import json
import math
import struct
import time

import numpy as np
import pytest

pytest.importorskip("foxglove")
websockets = pytest.importorskip("websockets")
from websockets.sync.client import connect  # noqa: E402

from racecav.common import keys, procs  # noqa: E402
from racecav.common.codec import encode  # noqa: E402
from racecav.common.messages import DriveCommand, Obstacle, ObstacleStates, Scan, VehicleState  # noqa: E402

CHANNELS = {"/scan": "foxglove.LaserScan", "/tf": "foxglove.FrameTransforms", "/cars": "foxglove.SceneUpdate",
            "/walls": "foxglove.SceneUpdate", "/cmd": "racecav.DriveCommand", "/latency": "racecav.Latency"}


def _varint(b: bytes, i: int) -> tuple[int, int]:
    v = shift = 0
    while True:
        c = b[i]
        i += 1
        v |= (c & 0x7F) << shift
        shift += 7
        if c < 0x80:
            return v, i


def protobuf_fields(b: bytes) -> dict[int, list]:
    """Top-level fields of a protobuf message (wire format only: no schema, no library)."""
    out: dict[int, list] = {}
    i = 0
    while i < len(b):
        tag, i = _varint(b, i)
        num, wt = tag >> 3, tag & 7
        if wt == 0:
            v, i = _varint(b, i)
        elif wt == 1:
            v, i = b[i:i + 8], i + 8
        elif wt == 5:
            v, i = b[i:i + 4], i + 4
        elif wt == 2:
            n, i = _varint(b, i)
            v, i = b[i:i + n], i + n
        else:
            raise ValueError(f"wire type {wt}")
        out.setdefault(num, []).append(v)
    return out


def test_viz_serves_every_channel(spawn, session, tmp_path):
    port = procs.free_port()
    mcap_path = tmp_path / "view.mcap"
    viz = spawn("viz", "--port", str(port), "--world", "intersection", "--mcap", str(mcap_path))
    procs.wait_alive(session, "car0", "viz", proc=viz)

    deadline = time.monotonic() + 10
    while True:  # alive (its token) comes a moment before the server of its setup listens
        try:
            ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=10)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)
    with ws:
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 10
        while set(channels) != set(CHANNELS) and time.monotonic() < deadline:
            m = ws.recv(timeout=5)
            if isinstance(m, str) and json.loads(m).get("op") == "advertise":
                channels.update({c["topic"]: c for c in json.loads(m)["channels"]})
        assert set(channels) == set(CHANNELS)
        for topic, schema in CHANNELS.items():
            c = channels[topic]
            assert c["encoding"] == ("json" if schema.startswith("racecav.") else "protobuf"), c
            assert c["schemaName"] == schema, c  # JSON ones named too, not generated
        subs = {i: topic for i, topic in enumerate(CHANNELS)}
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": i, "channelId": channels[t]["id"]} for i, t in subs.items()]}))
        time.sleep(0.5)

        ranges = np.linspace(0.5, 9.0, 170, dtype=np.float32)
        ranges[7] = np.inf
        scan = Scan(stamp_ns=5_000_000_000, seq=42, source="sim", angle_min=-math.pi / 4, angle_max=math.pi / 4,
                    angle_increment=math.pi / 2 / 169, range_min=0.1, range_max=12.0, ranges=ranges)
        cmd = DriveCommand(stamp_ns=5_001_000_000, source="policy", a_throttle=0.5, a_steer=-0.25, throttle=0.5,
                           steering_angle=-0.07, scan_seq=42, scan_stamp_ns=5_000_000_000, compute_ns=12_000)
        session.put(keys.topic("car0", keys.STATE), encode(VehicleState(stamp_ns=1, source="sim", x=1.5, y=-0.5, yaw=0.3)))
        session.put(keys.topic("car0", keys.OBSTACLES), encode(ObstacleStates(stamp_ns=1, obstacles=[
            Obstacle(id=3, x=4.0, y=0.0, yaw=math.pi)])))
        session.put(keys.topic("car0", keys.SCAN), encode(scan))
        time.sleep(0.1)
        session.put(keys.topic("car0", keys.CMD), encode(cmd))

        every: dict[str, list[bytes]] = {}

        def complete() -> bool:
            cars = every.get("/cars", [])
            return (set(every) == set(CHANNELS) and any(b"ego" in c for c in cars)
                    and any(b"obstacle-3" in c for c in cars))

        deadline = time.monotonic() + 10
        while not complete() and time.monotonic() < deadline:
            m = ws.recv(timeout=5)
            if isinstance(m, bytes) and m[0] == 0x01:  # messageData: op, subscription id, log time, payload
                sub_id, _log_time = struct.unpack_from("<IQ", m, 1)
                every.setdefault(subs[sub_id], []).append(m[13:])
    assert set(every) == set(CHANNELS), f"no message on {set(CHANNELS) - set(every)}"
    got = {t: msgs[0] for t, msgs in every.items()}

    f = protobuf_fields(got["/scan"])  # foxglove.LaserScan: 2 frame_id, 4/5 start/end angle, 6 ranges
    assert f[2] == [b"laser"]
    assert struct.unpack("<d", f[4][0])[0] == pytest.approx(-math.pi / 4)
    assert np.array_equal(np.frombuffer(f[6][0], "<f8").astype(np.float32), ranges)
    assert b"base_link" in got["/tf"] and b"laser" in got["/tf"]
    assert complete()  # the ego's box (from the state) and the obstacle's (from the obstacles)
    assert b"walls" in got["/walls"]
    c = json.loads(got["/cmd"])
    assert (c["a_steer"], c["steering_angle"], c["source"]) == (-0.25, pytest.approx(-0.07), "policy")
    lat = json.loads(got["/latency"])
    assert 0 <= lat["scan_to_cmd_ms"] < 5000 and lat["compute_ms"] == pytest.approx(0.012)

    assert procs.stop(viz) == 0
    from mcap.reader import make_reader

    with open(mcap_path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()} == CHANNELS
