"""The bus between real processes: a real router, real services, real Zenoh sessions."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from racecav.common import keys, procs
from racecav.common.client import get_status, live_services
from racecav.common.codec import encode
from racecav.common.messages import DriveCommand, Obstacle, ObstacleStates, Scan, VehicleState
from tests.test_bus_codec import scan

CAR = "car0"

SAMPLES = {
    "scan": scan(ranges=np.linspace(0.1, 11.9, 170, dtype=np.float32)),
    "cmd": DriveCommand(stamp_ns=7, seq=3, source="policy", a_throttle=0.25, a_steer=-0.5, throttle=0.25,
                        steering_angle=-0.13, scan_seq=2, scan_stamp_ns=6, compute_ns=4500),
    "state": VehicleState(stamp_ns=9, source="sim", x=1.5, y=-2.0, yaw=0.3, vx=1.2, yaw_rate=0.1),
    "obstacles": ObstacleStates(stamp_ns=11, obstacles=[Obstacle(id=1, x=3.0, y=0.5, yaw=3.1, speed=1.0)]),
}


def wait_until(pred, timeout=10.0, step=0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return False


@pytest.mark.parametrize("topic", list(SAMPLES))
def test_message_round_trips_between_processes(topic, session, spawn, router):
    """Publish from this process; a separate `racecav echo` process decodes and prints it."""
    msg = SAMPLES[topic]
    p = spawn("echo", topic, "--count", "1", "--name", f"echo-{topic}")
    procs.wait_alive(session, CAR, f"echo-{topic}", proc=p)
    key = keys.topic(CAR, topic)
    # Publish until the echo process got it (its subscription needs a moment to propagate).
    wait_until(lambda: (session.put(key, encode(msg)), p.poll() is not None)[1], timeout=15, step=0.2)
    assert p.wait(10) == 0
    printed = [ln for ln in p.log_path.read_text().splitlines() if ln.startswith("{")]
    assert json.loads(printed[0]) == msg.model_dump(mode="json")


def test_status_queryable_and_malformed_payloads(session, spawn):
    p = spawn("echo", "scan", "--name", "scanecho", "--quiet")
    procs.wait_alive(session, CAR, "scanecho", proc=p)
    key = keys.topic(CAR, "scan")
    good = encode(SAMPLES["scan"])
    bad = [os.urandom(64), b"", b"\x81\xa1v\x63", encode(SAMPLES["cmd"]),  # garbage, empty, wrong version, wrong type
           good[:-10], b"\x00" * 70000]                                      # truncated, oversize
    session.put(key, good, congestion_control=zenoh.CongestionControl.BLOCK)
    assert wait_until(lambda: get_status(session, CAR, "scanecho").received >= 1)
    # One payload at a time, blocking on congestion: a burst put with Zenoh's default (drop) may
    # lose a sample on a loaded machine, and this test counts every one.
    for n, payload in enumerate(bad, start=1):
        session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_until(lambda: get_status(session, CAR, "scanecho").invalid == n), f"bad payload {n}"
    st = get_status(session, CAR, "scanecho")
    assert st.service == "scanecho" and st.car == CAR and st.pid == p.pid
    assert st.received == 1 + len(bad) and st.last_error
    assert st.config_digest and st.uptime_s > 0
    # Still alive and working after the garbage.
    session.put(key, good, congestion_control=zenoh.CongestionControl.BLOCK)
    assert wait_until(lambda: get_status(session, CAR, "scanecho").info["printed"] == 2)
    assert p.poll() is None


def test_liveliness_disappears_when_killed(session, spawn):
    p = spawn("echo", "cmd", "--name", "victim", "--quiet")
    procs.wait_alive(session, CAR, "victim", proc=p)
    os.killpg(p.pid, signal.SIGKILL)
    assert wait_until(lambda: "victim" not in live_services(session, CAR, 0.5), timeout=20)


def test_sigterm_is_a_clean_shutdown(session, spawn):
    p = spawn("echo", "cmd", "--name", "polite", "--quiet")
    procs.wait_alive(session, CAR, "polite", proc=p)
    t0 = time.monotonic()
    assert procs.stop(p) == 0
    assert time.monotonic() - t0 < 5
    assert "polite stopped" in p.log_path.read_text()


def test_state_command_lists_services(session, spawn, router):
    p = spawn("echo", "state", "--name", "listed", "--quiet")
    procs.wait_alive(session, CAR, "listed", proc=p)
    out = subprocess.run(procs.racecav_cmd("state", "--json"), env=procs.bus_env(router),
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    rows = {r["service"]: r for r in json.loads(out.stdout)["services"]}
    assert {"listed", "router"} <= set(rows)
    assert rows["listed"]["received"] == 0 and "invalid" in rows["listed"]
    missing = subprocess.run(procs.racecav_cmd("state", "nosuch"), env=procs.bus_env(router),
                             capture_output=True, text=True, timeout=30)
    assert missing.returncode == 1


def test_sd_notify_ready(tmp_path, router):
    """Under systemd (NOTIFY_SOCKET set) a service says READY=1 once it is on the bus."""
    import socket as so

    path = str(tmp_path / "notify.sock")
    sock = so.socket(so.AF_UNIX, so.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(20)
    p = procs.start(["echo", "cmd", "--name", "notified", "--quiet"],
                    procs.bus_env(router, extra={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "400000"}))
    try:
        msgs = {sock.recv(100).decode() for _ in range(2)}
        assert msgs == {"READY=1", "WATCHDOG=1"}
    finally:
        procs.stop(p)
        sock.close()


def test_invalid_config_exits_2_naming_the_field(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[bus]\ncar = "car 0!"\n')
    out = subprocess.run(procs.racecav_cmd("--config", str(bad), "state"), capture_output=True, text=True)
    assert out.returncode == 2 and "bus.car" in out.stderr
    bad.write_text('[bus]\nnot_a_field = 1\n')
    out = subprocess.run(procs.racecav_cmd("state", "--config", str(bad)), capture_output=True, text=True)
    assert out.returncode == 2 and "bus.not_a_field" in out.stderr
    env = dict(os.environ, RACECAV_BUS__STATUS_LOG_PERIOD_S="-1")
    out = subprocess.run(procs.racecav_cmd("state"), capture_output=True, text=True, env=env)
    assert out.returncode == 2 and "bus.status_log_period_s" in out.stderr
    bad.write_text("[bus\n")
    out = subprocess.run(procs.racecav_cmd("--config", str(bad), "state"), capture_output=True, text=True)
    assert out.returncode == 2 and "invalid TOML" in out.stderr
