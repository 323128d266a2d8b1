"""The deployed bus is secure by default: the units' ExecStart lines run as processes with the
installed config (login, mutual TLS, default-deny access control)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time

import numpy as np
import pytest
import zenoh

from racecav.common import keys, procs
from racecav.common.client import get_status, live_services
from racecav.common.codec import decode, encode
from racecav.common.lidar import make_scan
from racecav.common.messages import DriveCommand, Scan
from tests.deploy_support import DeployedCar, wait_until

CAR = "car0"


def outward_ip() -> str | None:
    """This machine's IPv4 address on a non-loopback interface (None if it has none)."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))  # a UDP connect only picks the route: nothing is sent
            ip = s.getsockname()[0]
    except OSError:
        return None
    return None if ip.startswith("127.") else ip


OUTWARD_IP = outward_ip()


def command(source: str, seq: int, throttle: float) -> bytes:
    return encode(DriveCommand(stamp_ns=time.monotonic_ns(), seq=seq, source=source, a_throttle=throttle,
                               a_steer=0.1, throttle=throttle, steering_angle=0.05))


@pytest.fixture(scope="module")
def car(tmp_path_factory):
    root = tmp_path_factory.mktemp("car")
    hosts = ["localhost", "127.0.0.1"] + ([OUTWARD_IP] if OUTWARD_IP else [])
    c = DeployedCar(root, hosts=hosts, extra_env={"RACECAV_ACTUATOR__PORT": str(root / "vesc"),
                                     "RACECAV_ACTUATOR__TIMEOUT_S": "3.0"})  # see the stop check
    try:
        c.start("router")
        c.wait_ready("router", 30)
        yield c
    finally:
        c.stop_all()


def test_router_unit_reports_ready_and_feeds_the_watchdog(car):
    # Type=notify + WatchdogSec: READY=1 once listening, then WATCHDOG=1 well within WatchdogSec.
    assert wait_until(lambda: "WATCHDOG=1" in car.notify["router"].poll(), timeout=5)
    msgs = car.notify["router"].poll()
    assert msgs.index("READY=1") < msgs.index("WATCHDOG=1")


def test_no_login_no_bus(car):
    with pytest.raises(zenoh.ZError):
        car.session(None)
    with pytest.raises(zenoh.ZError):
        car.session("monitor", password="not-the-password")
    with pytest.raises(zenoh.ZError):  # a real account name is not enough either
        car.session("policy", password="")
    # Over TLS: the right password without a client certificate is refused (mutual TLS) ...
    with pytest.raises(zenoh.ZError):
        car.session("monitor", tls=True, cert=False)
    # ... and a certificate without the password too.
    with pytest.raises(zenoh.ZError):
        car.session(None, tls=True)
    with car.session("monitor", tls=True) as s:
        assert "router" in live_services(s, CAR)


def test_state_command_needs_the_monitor_login(car):
    base = {"PATH": "/usr/bin:/bin", "RACECAV_CONFIG": str(car.lay.etc / "racecav.toml"),
            "RACECAV_BUS__CONNECT": f'["{car.endpoint}"]'}
    cmd = procs.racecav_cmd("state", "--json")
    ok = subprocess.run(cmd, env={**base, **car.account_env("monitor")}, capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
    assert [r["service"] for r in json.loads(ok.stdout)["services"]] == ["router"]
    anon = subprocess.run(cmd, env=base, capture_output=True, text=True, timeout=60)
    assert anon.returncode == 1 and "cannot join the bus" in anon.stderr and "without a login" in anon.stderr


ACCOUNTS_ORDER = ("policy", "baseline", "actuator", "teleop", "sensor", "sim")


def test_remote_config_made_by_credentials_works_over_mutual_tls(car):
    # credentials/monitor-remote.toml is what a laptop uses (only the endpoint differs here).
    remote = car.lay.etc / "credentials" / "monitor-remote.toml"
    env = {"PATH": "/usr/bin:/bin", "RACECAV_BUS__CONNECT": f'["tls/localhost:{car.tls_port}"]'}
    r = subprocess.run(procs.racecav_cmd("--config", str(remote), "state", "--json"), env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "router" in [s["service"] for s in json.loads(r.stdout)["services"]]


def test_only_sensor_and_sim_accounts_publish_scans(car):
    got: list[str] = []
    with car.session("monitor") as mon:
        sub = mon.declare_subscriber(keys.topic(CAR, keys.SCAN), lambda s: got.append(s.payload.to_bytes()))
        try:
            for i, account in enumerate(ACCOUNTS_ORDER):
                with car.session(account) as s:
                    time.sleep(0.3)
                    for k in range(5):  # seq says who sent it
                        scan = make_scan(np.full(170, 2.0, np.float32), k, 100 * i + k, "real")
                        s.put(keys.topic(CAR, keys.SCAN), encode(scan))
                        time.sleep(0.02)
                    time.sleep(0.3)
        finally:
            sub.undeclare()
    senders = {ACCOUNTS_ORDER[decode(b, Scan).seq // 100] for b in got}
    assert senders == {"sensor", "sim"}, senders


def test_car_accounts_cannot_drive_from_the_network(car):
    # The policy's password is useless off the car: its subject matches only through loopback.
    # (Its login is still accepted, so this also shows denied puts vanish silently.)
    if OUTWARD_IP is None:
        pytest.skip("this machine has no non-loopback IPv4 address: cannot connect from 'the network'")

    cmd_key = keys.topic(CAR, keys.CMD)
    got: list[str] = []
    with car.session("monitor") as mon:
        sub = mon.declare_subscriber(cmd_key, lambda s: got.append(decode(s.payload.to_bytes(), DriveCommand).source))
        try:
            for tag, account, kw in (("policy@net", "policy", dict(tls=OUTWARD_IP, cert="teleop")),
                                     ("policy@lo", "policy", {}),
                                     ("teleop@net", "teleop", dict(tls=OUTWARD_IP))):
                with car.session(account, **kw) as s:
                    time.sleep(0.3)
                    for k in range(5):
                        s.put(cmd_key, command(tag, k, 0.5))
                        time.sleep(0.02)
                    time.sleep(0.3)
        finally:
            sub.undeclare()
    assert set(got) == {"policy@lo", "teleop@net"}, got


@pytest.fixture(scope="module")
def vesc(car, tmp_path_factory):
    """The VESC emulator on the path the installed config names; yields its frame log."""
    d = tmp_path_factory.mktemp("vesc")
    vlog = d / "vesc.jsonl"
    emu = procs.start(["emulate", "vesc", "--link", str(car.root / "vesc"), "--log", str(vlog), "--quiet"],
                      procs.bus_env(car.endpoint), d / "emu.log")
    try:
        assert wait_until((car.root / "vesc").exists)
        yield vlog
    finally:
        procs.stop(emu)


def frames(vlog, since: int = 0) -> list[dict]:
    return [json.loads(ln) for ln in vlog.read_text().splitlines()[since:]]


def mapping():
    from racecav.common.config import load_config
    from racecav.common.vehicle import load_car
    from racecav.services.actuator.control import Mapping

    return Mapping(load_config().actuator, load_car("slash"))


def drive(session, source: str, throttle: float, n: int = 15) -> None:
    """Commands from a declared express publisher, as the controllers send them (it only sends
    once it has heard of the actuator's subscription: the ACL must let that through too)."""
    pub = session.declare_publisher(keys.topic(CAR, keys.CMD), express=True)
    time.sleep(0.3)
    try:
        for k in range(n):
            pub.put(command(source, k, throttle))
            time.sleep(0.02)
    finally:
        pub.undeclare()


def test_non_controller_accounts_never_reach_the_actuator(car, vesc):
    start = len(frames(vesc))
    car.start("actuator")
    car.wait_ready("actuator", 30)
    with car.session("monitor") as mon, car.session("policy") as pol:
        procs.wait_alive(mon, CAR, "actuator")
        info = lambda: get_status(mon, CAR, "actuator").info  # noqa: E731
        drive(pol, "policy", 0.5)  # the controller's commands reach the motor
        assert wait_until(lambda: info()["accepted"] >= 10, timeout=5)
        accepted = info()["accepted"]
        # Everyone else, even claiming to be the policy (the source field is self-declared):
        for account in ("sensor", "sim", "actuator", "monitor"):
            with car.session(account) as s:
                drive(s, "policy", 0.9)
        time.sleep(0.3)
        st = info()
        assert st["accepted"] == accepted and st["refused"] == 0 and st["malformed"] == 0
        # The baseline account may publish commands, but the actuator only obeys its
        # configured controller (actuator.controller = policy): refused, counted.
        with car.session("baseline") as s:
            drive(s, "baseline", 0.9, n=5)
        assert wait_until(lambda: info()["refused"] >= 3, timeout=3)
        assert info()["accepted"] == accepted
        # Stopping the unit (SIGTERM, as systemctl stop) while the policy drives leaves the
        # motor braked and the steering centred at once (the 3 s watchdog cannot be the cause).
        drive(pol, "policy", 0.5, n=10)
        assert car.stop("actuator") == 0
    recs = frames(vesc, start)
    m = mapping()
    # The 0.9 commands never reached the VESC: every drive frame is the policy's 0.5.
    drive_rpm = [r["value"] for r in recs if r["name"] == "SET_RPM" and r["value"] > 0]
    assert drive_rpm and all(abs(v - m.erpm(0.5)) <= 1 for v in drive_rpm)
    last_drive = max(i for i, r in enumerate(recs) if r["name"] == "SET_RPM" and r["value"] > 0)
    tail = recs[last_drive + 1:]
    assert [r["name"] for r in tail[-2:]] == ["SET_CURRENT_BRAKE", "SET_SERVO_POS"]
    assert tail[-1]["value"] == pytest.approx(m.servo(0.0), abs=1e-3)
    assert tail[-2]["t"] - recs[last_drive]["t"] < 1.0


def test_a_killed_actuator_still_leaves_the_motor_neutral(car, vesc):
    # SIGKILL (or a watchdog abort): no teardown runs, the VESC keeps the last command until
    # systemd runs the unit's ExecStopPost (`racecav actuator --neutral`).
    car.start("actuator")
    car.wait_ready("actuator", 30)
    with car.session("monitor") as mon, car.session("policy") as pol:
        procs.wait_alive(mon, CAR, "actuator")
        drive(pol, "policy", 0.5, n=10)
        assert get_status(mon, CAR, "actuator").info["driving"] == "controller"
        start = len(frames(vesc))
        os.killpg(car.procs["actuator"].pid, signal.SIGKILL)
        car.procs["actuator"].wait(10)
    time.sleep(0.3)
    after_kill = frames(vesc, start)
    assert not any(r["name"] == "SET_CURRENT_BRAKE" for r in after_kill)  # nothing stopped it yet
    assert car.run_command("actuator", "ExecStopPost") == 0
    recs = frames(vesc, start)[len(after_kill):]
    assert [r["name"] for r in recs] == ["SET_CURRENT_BRAKE", "SET_SERVO_POS"]
    assert recs[1]["value"] == pytest.approx(mapping().servo(0.0), abs=1e-3)
