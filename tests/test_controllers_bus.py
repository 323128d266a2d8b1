"""Both controllers are interchangeable processes on the bus: same input key, same output key and
message; the sim service (lockstep) is driven by either without knowing which one runs."""

from __future__ import annotations

import time

import pytest

from racecav.common import keys, procs
from racecav.common.client import get_status
from racecav.common.codec import decode
from racecav.common.messages import DriveCommand, VehicleState
from tests.test_controllers_policy import random_policy_file

pytest.importorskip("casadi")

# Interchangeability, not avoidance (tests/test_controllers_baseline.py covers that): an empty road.
EMPTY = """
name = "empty-road"
world = "intersection"
duration_s = 10.0
[ego]
x = -6.0
y = 0.0
yaw_deg = 0.0
speed = 1.0
[success]
min_progress_m = 5.0
"""


def _collect(session, key, cls):
    items = []
    sub = session.declare_subscriber(key, lambda s: items.append(decode(s.payload.to_bytes(), cls)))
    return items, sub


def _wait(pred, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.05)
    raise TimeoutError(what)


def test_policy_and_baseline_drive_the_sim_interchangeably(spawn, session, tmp_path):
    scenario = tmp_path / "empty.toml"
    scenario.write_text(EMPTY)
    sim = spawn("sim", "--scenario", str(scenario), "--mode", "lockstep")
    procs.wait_alive(session, "car0", "sim", proc=sim)
    cmds, sub_c = _collect(session, keys.topic("car0", keys.CMD), DriveCommand)
    states, sub_s = _collect(session, keys.topic("car0", keys.STATE), VehicleState)

    # the baseline drives the car along its lane
    base = spawn("baseline")
    _wait(lambda: len(states) > 45 or any(s.collided for s in states), 90, "baseline did not drive 45 steps")
    st = get_status(session, "car0", "sim")
    assert st.info["last_source"] == "baseline" and not st.info["collided"], \
        " ".join(f"{s.x:.2f},{s.y:.2f},{s.vx:.2f}" for s in states)
    assert states[-1].x - states[0].x > 3.0           # it drove (about 1 m/s) ...
    assert max(abs(s.y) for s in states) < 0.2        # ... in its lane
    b = get_status(session, "car0", "baseline")
    assert b.info["answered"] >= 45 and b.info["iterations_mean"] >= 1
    assert b.info["solve_ms_median"] > 0 and b.info["ego_source"] == "state"
    base_cmds = [c for c in cmds if c.source == "baseline"]
    assert base_cmds and all(c.scan_seq >= 0 for c in base_cmds)
    procs.stop(base)

    # the policy takes over on the same keys: the sim keeps stepping with its commands
    n_before = len(states)
    pol = spawn("policy", "--model", str(random_policy_file(tmp_path / "pol.npz")))
    _wait(lambda: len(states) > n_before + 10, 60, "policy did not drive 10 steps")
    assert get_status(session, "car0", "sim").info["last_source"] == "policy"
    pol_cmds = [c for c in cmds if c.source == "policy"]
    assert pol_cmds
    # same message type, same fields filled the same way
    for c in (base_cmds[-1], pol_cmds[-1]):
        assert type(c) is DriveCommand and c.scan_stamp_ns >= 0 and c.compute_ns > 0
        assert 0.0 <= c.throttle <= 1.0 and -0.27 <= c.steering_angle <= 0.32
    procs.stop(pol)
    sub_c.undeclare()
    sub_s.undeclare()
