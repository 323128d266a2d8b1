"""End to end with the command line: `racecav emulate rplidar` + `racecav sensor` publish Scans on a real
router; `racecav emulate vesc` + `racecav actuator` stop the motor when the controller goes quiet."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from racecav.common import keys, procs
from racecav.common.client import get_status
from racecav.common.codec import decode, encode
from racecav.common.lidar import LidarSpec, published_scan, ray_angles
from racecav.common.messages import DriveCommand, Scan
from racecav.services.sensor.emulator import WallScene, default_walls

CAR = "car0"


def wait_until(pred, timeout=10.0, step=0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return False


@pytest.mark.parametrize("kind", ["paper", "wide"])
def test_emulated_rplidar_to_scans_on_the_bus(spawn, session, tmp_path, kind):
    """``kind``: SensorConfig.scan (wide: the +-89.7 deg scan a wide-view policy takes its rays from)."""
    link = tmp_path / "rplidar"
    spawn("emulate", "rplidar", "--link", str(link), "--reset-s", "0.1")
    assert wait_until(link.exists)
    scans: list[tuple[float, Scan]] = []
    lock = threading.Lock()

    def on_scan(sample):
        with lock:
            scans.append((time.monotonic(), decode(sample.payload.to_bytes(), Scan)))

    sub = session.declare_subscriber(keys.topic(CAR, keys.SCAN), on_scan)
    try:
        p = spawn("sensor", "--port", str(link), env={"RACECAV_SENSOR__RESET_WAIT_S": "0.2",
                                                      "RACECAV_SENSOR__SPINUP_S": "0.05",
                                                      "RACECAV_SENSOR__SCAN": kind})
        procs.wait_alive(session, CAR, "sensor", proc=p)
        assert wait_until(lambda: len(scans) >= 12, timeout=15), f"{len(scans)} scans"
    finally:
        sub.undeclare()
    with lock:
        got = list(scans)
    rate = (len(got) - 2) / (got[-1][0] - got[1][0])
    assert 7 < rate < 13  # once per revolution
    spec = published_scan(LidarSpec(), kind)
    truth = WallScene(default_walls()).ranges_mm(-np.degrees(ray_angles(spec).astype(np.float64))) / 1000.0
    seqs = [s.seq for _, s in got]
    assert seqs == sorted(seqs)
    for _, s in got[-3:]:
        assert s.source == "real" and s.ranges.shape == (spec.n_rays,) and s.angle_min == pytest.approx(spec.angle_min)
        err = np.abs(s.ranges - truth)
        assert np.median(err) < 0.002 and np.mean(err < 0.01) > 0.97
        assert abs(time.monotonic_ns() - s.stamp_ns) < 5e9  # monotonic stamps, like every real message
    st = get_status(session, CAR, "sensor")
    assert st.info["state"] == "scanning" and st.info["mode_name"] == "DenseBoost"
    assert st.published >= 12 and st.info["parser_checksum"] == 0


def test_emulated_vesc_neutral_when_controller_dies(spawn, session, tmp_path):
    link, log = tmp_path / "vesc", tmp_path / "vesc.jsonl"
    spawn("emulate", "vesc", "--link", str(link), "--log", str(log), "--quiet")
    assert wait_until(link.exists)
    p = spawn("actuator", "--port", str(link), env={"RACECAV_ACTUATOR__TIMEOUT_S": "0.1"})
    procs.wait_alive(session, CAR, "actuator", proc=p)
    pub = session.declare_publisher(keys.topic(CAR, keys.CMD), express=True)
    for k in range(25):  # the "controller": 50 Hz, then it dies
        pub.put(encode(DriveCommand(stamp_ns=time.monotonic_ns(), seq=k, source="policy", a_throttle=0.6,
                                    a_steer=0.2, throttle=0.6, steering_angle=0.2)))
        time.sleep(0.02)
    time.sleep(0.4)
    recs = [json.loads(ln) for ln in log.read_text().splitlines()]
    drive = [r for r in recs if r["name"] == "SET_RPM" and r["value"] > 0]
    assert drive, "commands never reached the VESC"
    last_value = drive[-1]["value"]
    # The last command's arrival is the first frame of the final run of identical drive frames;
    # with constant commands that is the arrival of the last command at most one resend earlier.
    t_last = drive[-1]["t"]
    stop = next(r for r in recs if r["name"] == "SET_CURRENT_BRAKE" and r["t"] > t_last)
    assert stop["t"] - t_last <= 0.125 and last_value > 0
    servo = next(r for r in recs if r["name"] == "SET_SERVO_POS" and r["t"] >= stop["t"])
    assert servo["value"] == pytest.approx(0.530, abs=1e-3)


@pytest.mark.parametrize("timeout_s", [0.25])
def test_whole_chain_without_hardware(spawn, session, tmp_path, timeout_s):
    """emulate rplidar -> sensor -> controller (scripted, as the policy) -> actuator -> emulate vesc.

    The controller answers each 10 Hz scan, so commands come every ~100 ms: the watchdog must be
    longer than that (here 250 ms) or it brakes between commands (see docs/hardware.md).
    """
    lidar, vesc, log = tmp_path / "rplidar", tmp_path / "vesc", tmp_path / "vesc.jsonl"
    spawn("emulate", "rplidar", "--link", str(lidar), "--reset-s", "0.1")
    spawn("emulate", "vesc", "--link", str(vesc), "--log", str(log), "--quiet")
    assert wait_until(lambda: lidar.exists() and vesc.exists())
    act = spawn("actuator", "--port", str(vesc), env={"RACECAV_ACTUATOR__TIMEOUT_S": str(timeout_s)})
    procs.wait_alive(session, CAR, "actuator", proc=act)
    ctl = spawn("scripted", "--program", "0.6,0.1,20", "--then", "stop", "--source", "policy")
    procs.wait_alive(session, CAR, "scripted", proc=ctl)
    sen = spawn("sensor", "--port", str(lidar), env={"RACECAV_SENSOR__RESET_WAIT_S": "0.2",
                                                     "RACECAV_SENSOR__SPINUP_S": "0.05"})
    assert wait_until(lambda: get_status(session, CAR, "scripted").info.get("answered", 0) >= 20, timeout=20)
    time.sleep(timeout_s + 0.3)
    recs = [json.loads(ln) for ln in log.read_text().splitlines()]
    drive = [r for r in recs if r["name"] == "SET_RPM" and r["value"] > 0]
    assert len(drive) >= 20
    t0, t1 = drive[0]["t"], drive[-1]["t"]
    brakes_while_driving = [r for r in recs if r["name"] == "SET_CURRENT_BRAKE" and t0 < r["t"] < t1]
    assert not brakes_while_driving
    stop = next(r for r in recs if r["name"] == "SET_CURRENT_BRAKE" and r["t"] > t1)
    assert stop["t"] - t1 <= timeout_s + 0.03
    st = get_status(session, CAR, "actuator")
    assert st.info["accepted"] >= 20 and st.info["driving"] == "timeout"


def test_record_scans_from_the_bus_for_replay(spawn, session, tmp_path):
    from racecav.common.lidar import make_scan
    from racecav.services.sensor.emulator import ReplayScene

    out = tmp_path / "scans.npz"
    p = spawn("emulate", "record-scans", "--count", "3", "--out", str(out), "--timeout", "20")
    key = keys.topic(CAR, keys.SCAN)
    sent = [np.full(170, 1.0 + k, np.float32) for k in range(3)]
    k = 0
    # The recorder's subscription takes a moment to reach the router: publish until it has all 3.
    while p.poll() is None and k < 200:
        session.put(key, encode(make_scan(sent[min(k, 2)], k, k, "sim")))
        k += 1
        time.sleep(0.05)
    assert p.wait(10) == 0
    scene = ReplayScene(out)
    assert scene.ranges.shape == (3, 170) and scene.angle_min == pytest.approx(-np.pi / 4)
    # Straight ahead (device 0 deg) in each recorded revolution.
    got = [scene.ranges_mm(np.array([0.0]), rev)[0] for rev in range(3)]
    assert got[-1] == pytest.approx(3000.0) and got == sorted(got)
