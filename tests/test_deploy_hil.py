"""Hardware-in-the-loop on the deployed car: swapping racecav-sensor and racecav-sim at runtime
keeps the policy (and the actuator) running; `racecav state` shows which scan source is live; a
killed service restarted re-joins the bus; the baseline unit replaces the policy.

Units run as processes from their ExecStart lines with the installed, secured config (see
tests/deploy_support.py); the lidar and the VESC are the byte-exact emulators on ptys.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess

import numpy as np
import pytest

from racecav.common import procs
from racecav.common.client import get_status, live_services
from tests.deploy_support import DeployedCar, wait_until

CAR = "car0"


@pytest.fixture
def car(tmp_path):
    # A policy that always drives gently ahead (zero weights, bias = the action): its commands
    # are easy to recognise and independent of what it sees.
    model = tmp_path / "ahead.npz"
    np.savez(model, w0=np.zeros((170, 64), np.float32), b0=np.zeros(64, np.float32),
             w1=np.zeros((64, 64), np.float32), b1=np.zeros(64, np.float32),
             w2=np.zeros((64, 2), np.float32), b2=np.array([-0.4, 0.0], np.float32))
    c = DeployedCar(tmp_path, extra_env={
        "RACECAV_SENSOR__PORT": str(tmp_path / "rplidar"), "RACECAV_SENSOR__RESET_WAIT_S": "0.2",
        "RACECAV_SENSOR__SPINUP_S": "0.05", "RACECAV_ACTUATOR__PORT": str(tmp_path / "vesc"),
        "RACECAV_ACTUATOR__TIMEOUT_S": "0.3", "RACECAV_POLICY__MODEL": str(model),
        "RACECAV_SIM__ON_END": "reset", "RACECAV_ACTUATOR__SIM_SCANS_DRIVE": "true"})  # car on a stand
    emus = []
    try:
        c.start("router")
        c.wait_ready("router", 30)
        env = procs.bus_env(c.endpoint)
        emus.append(procs.start(["emulate", "rplidar", "--link", str(tmp_path / "rplidar"), "--reset-s", "0.1"],
                                env, tmp_path / "logs/emu-rplidar.log"))
        emus.append(procs.start(["emulate", "vesc", "--link", str(tmp_path / "vesc"), "--quiet"], env,
                                tmp_path / "logs/emu-vesc.log"))
        assert wait_until(lambda: (tmp_path / "rplidar").exists() and (tmp_path / "vesc").exists())
        yield c
    finally:
        c.stop_all()
        for p in emus:
            procs.stop(p)


def state(car: DeployedCar) -> dict:
    """`racecav state --json` with the monitor's login, as an operator runs it on the car."""
    env = {"PATH": os.environ.get("PATH", ""), "RACECAV_CONFIG": str(car.lay.etc / "racecav.toml"),
           "RACECAV_BUS__CONNECT": f'["{car.endpoint}"]', **car.account_env("monitor")}
    r = subprocess.run(procs.racecav_cmd("state", "--json"), env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return {s["service"]: s for s in json.loads(r.stdout)["services"]}


def test_sensor_sim_swap_keeps_the_policy_driving_and_state_shows_the_source(car):
    for unit in ("actuator", "policy", "sensor"):
        car.start(unit)
    for unit in ("actuator", "policy", "sensor"):
        car.wait_ready(unit, 120)
    with car.session("monitor") as mon:
        policy = lambda: get_status(mon, CAR, "policy")  # noqa: E731
        accepted = lambda: get_status(mon, CAR, "actuator").info["accepted"]  # noqa: E731
        assert wait_until(lambda: policy().info["answered"] >= 10, timeout=30), car.log("policy")
        st = policy()
        assert st.info["scan_source"] == "real" and accepted() >= 5
        pid = st.pid

        # HIL: `systemctl start racecav-sim` stops racecav-sensor (Conflicts=), starts the sim.
        car.stop("sensor")
        car.start("sim")
        car.wait_ready("sim", 180)
        answered, acc = policy().info["answered"], accepted()
        assert wait_until(lambda: policy().info["answered"] >= answered + 10, timeout=60), car.log("sim")
        st = policy()
        assert st.pid == pid and car.procs["policy"].poll() is None  # the controller never restarted
        assert st.info["scan_source"] == "sim" and accepted() > acc  # sim scans -> policy -> real actuator
        live = state(car)
        assert {"router", "actuator", "policy", "sim"} <= set(live) and "sensor" not in live
        assert live["policy"]["info"]["scan_source"] == "sim" and live["policy"]["pid"] == pid
        assert live["sim"]["outputs"][f"racecav/{CAR}/scan"]["source"] == "sim"

        # ...and back to the real lidar.
        car.stop("sim")
        car.start("sensor")
        car.wait_ready("sensor", 60)
        assert wait_until(lambda: policy().info["scan_source"] == "real", timeout=30)
        answered = policy().info["answered"]
        assert wait_until(lambda: policy().info["answered"] >= answered + 5, timeout=30)
        assert policy().pid == pid

        # A crashed service (SIGKILL: no clean shutdown) leaves the bus; restarted, as
        # Restart=on-failure does, it joins again and `racecav state` shows its new process.
        os.killpg(car.procs["policy"].pid, signal.SIGKILL)
        car.procs["policy"].wait(10)
        assert wait_until(lambda: "policy" not in live_services(mon, CAR), timeout=10)
        car.start("policy")
        car.wait_ready("policy", 120)
        assert wait_until(lambda: "policy" in live_services(mon, CAR), timeout=10)
        assert wait_until(lambda: policy().info["answered"] >= 3, timeout=30)
        live = state(car)
        assert live["policy"]["pid"] == car.procs["policy"].pid != pid
        assert live["policy"]["info"]["scan_source"] == "real"

        # The other controller: `systemctl start racecav-baseline` stops the policy (Conflicts=).
        # Its account may drive, but the actuator obeys only actuator.controller (= policy here).
        car.stop("policy")
        refused = get_status(mon, CAR, "actuator").info["refused"]
        car.start("baseline")
        car.wait_ready("baseline", 180)
        assert wait_until(lambda: get_status(mon, CAR, "baseline").info["answered"] >= 5, timeout=60), \
            car.log("baseline")
        assert get_status(mon, CAR, "baseline").info["scan_source"] == "real"
        assert wait_until(lambda: get_status(mon, CAR, "actuator").info["refused"] > refused, timeout=10)
        assert "policy" not in live_services(mon, CAR)
