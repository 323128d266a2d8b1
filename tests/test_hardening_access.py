"""Hardening (issue 19): who may control what, under the secured router (installed config:
login, mutual TLS, default-deny access control), tried with every account.

- the simulator's control queries (reset, scenario) answer the operator account only;
- status queries answer every account (monitor included);
- the e-stop accepts the operator and teleop only (clearing it lets the car drive again);
- the monitor account is read-only: nothing it puts reaches anyone."""

from __future__ import annotations

import json
import time

import pytest

from racecav.common import keys
from racecav.common.client import get_status, query
from racecav.deploy.credentials import ACCOUNTS
from tests.deploy_support import DeployedCar

CAR = "car0"
SIM_CONTROL = ("operator",)
ESTOP_ALLOWED = ("operator", "teleop")


@pytest.fixture(scope="module")
def car(tmp_path_factory):
    root = tmp_path_factory.mktemp("car")
    c = DeployedCar(root, extra_env={"RACECAV_SIM__SCENARIO": "head-to-head"})
    try:
        c.start("router")
        c.wait_ready("router", 30)
        c.start("sim")
        c.wait_ready("sim", 90)
        yield c
    finally:
        c.stop_all()


def test_sim_control_only_for_the_operator(car):
    for account in ACCOUNTS:
        with car.session(account) as s:
            time.sleep(0.2)
            st = get_status(s, CAR, "sim", timeout=5)  # reading: everyone
            assert st.service == "sim"
            reset = keys.service_key(CAR, "sim", "reset")
            scen = keys.service_key(CAR, "sim", "scenario")
            if account in SIM_CONTROL:
                out = json.loads(query(s, reset, json.dumps({"seed": 11}).encode(), timeout=10))
                assert out["seed"] == 11
                assert "available" in json.loads(query(s, scen, None, timeout=5))
            else:  # denied queries vanish: no reply, and the episode did not change
                episode = st.info["episode"]
                for key, payload in ((reset, json.dumps({"seed": 99}).encode()),
                                     (scen, json.dumps({"name": "left-to-right"}).encode())):
                    with pytest.raises(RuntimeError, match="no reply"):
                        query(s, key, payload, timeout=0.7)
                after = get_status(s, CAR, "sim", timeout=5).info
                assert after["episode"] == episode and after["scenario"] == st.info["scenario"], account


def test_estop_operator_and_teleop_only_and_monitor_is_read_only(car):
    got: list[tuple[str, bytes]] = []
    with car.session("operator") as op:
        subs = [op.declare_subscriber(keys.topic(CAR, leaf), lambda smp: got.append((str(smp.key_expr),
                                                                                   smp.payload.to_bytes())))
                for leaf in (keys.ESTOP, keys.CMD, keys.SCAN, "monitor/x")]
        try:
            for account in ACCOUNTS:
                with car.session(account) as s:
                    time.sleep(0.3)
                    s.put(keys.topic(CAR, keys.ESTOP), f"stop by {account}".encode())
                    if account == "monitor":
                        for leaf in (keys.CMD, keys.SCAN, "monitor/x"):
                            s.put(keys.topic(CAR, leaf), b"monitor was here")
                    time.sleep(0.3)
            estops = {p.decode().split()[-1] for k, p in got if k.endswith("/estop")}
            assert estops == set(ESTOP_ALLOWED), estops
            assert not [p for _k, p in got if p == b"monitor was here"]
            # the router's copy of the latch follows the allowed puts only
            assert json.loads(query(op, keys.service_key(CAR, "router", "estop"), timeout=5))["latched"] is True
            op.put(keys.topic(CAR, keys.ESTOP), b"clear")
            time.sleep(0.2)
            with car.session("monitor") as mon:
                mon.put(keys.topic(CAR, keys.ESTOP), b"stop")  # denied: the latch stays clear
                time.sleep(0.3)
                assert json.loads(query(mon, keys.service_key(CAR, "router", "estop"), timeout=5))["latched"] is False
        finally:
            for sub in subs:
                sub.undeclare()
