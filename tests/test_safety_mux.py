"""The actuator's mux (services/actuator/control.py): every pair of inputs, who wins, when each
times out; the sim and the actuator share the class, so this is the order of both."""

from __future__ import annotations

import itertools

import pytest

from racecav.common import keys
from racecav.common.config import ActuatorConfig
from racecav.common.messages import DriveCommand
from racecav.services.actuator.control import PRIORITY, CommandMux, Mapping
from racecav.services.actuator import vesc_protocol as vp

ACFG = ActuatorConfig(controller="policy", timeout_s=0.25, teleop_hold_s=0.5, safety_timeout_s=0.2,
                      ros_timeout_s=0.3)
# input -> (source it must carry, reason while it drives, its timeout)
INPUTS = {
    "estop": (None, "estop", None),
    keys.SAFETY: ("safety", "safety", 0.2),
    keys.TELEOP: ("teleop", "teleop", 0.25),
    keys.DRIVE_ROS: ("ros", "ros", 0.3),
    keys.CMD: ("policy", "controller", 0.25),
}
ORDER = list(INPUTS)  # highest priority first


def cmd(source: str, throttle: float = 0.5) -> DriveCommand:
    return DriveCommand(stamp_ns=0, source=source, a_throttle=throttle, a_steer=0.1, throttle=throttle,
                        steering_angle=0.1)


def give(mux: CommandMux, name: str, t: float) -> DriveCommand | None:
    if name == "estop":
        mux.estop(b"stop")
        return None
    c = cmd(INPUTS[name][0])
    assert mux.offer(c, name, t)
    return c


def test_order_is_the_documented_one():
    assert list(PRIORITY) == ORDER[1:]


@pytest.mark.parametrize("hi,lo", list(itertools.combinations(ORDER, 2)))
def test_every_pair_higher_wins_then_lower_after_timeout(hi, lo):
    mux = CommandMux.from_config(ACFG)
    c_lo = give(mux, lo, 0.0)
    c_hi = give(mux, hi, 0.0)
    d = mux.decide(0.01)
    assert d.reason == INPUTS[hi][1]
    assert d.cmd is c_hi
    # the other order of arrival gives the same winner
    mux2 = CommandMux.from_config(ACFG)
    give(mux2, hi, 0.0)
    give(mux2, lo, 0.0)
    assert mux2.decide(0.01).reason == INPUTS[hi][1]
    if hi == "estop":
        # the latch has no timeout; "clear" hands over to the lower input still fresh
        assert mux.decide(100.0).reason == "estop"
        mux.estop(b"clear")
        assert mux.decide(0.02).cmd is c_lo
        return
    t_hi = INPUTS[hi][2]
    assert d.deadline == pytest.approx(t_hi)
    assert mux.decide(t_hi - 1e-3).reason == INPUTS[hi][1]
    # the higher input expires: the lower one drives while it is fresh, then its own timeout
    t_lo = INPUTS[lo][2]
    if hi == keys.TELEOP:
        # teleop holds ROS drive and the controller off for teleop_hold_s after its last command
        assert mux.decide(t_hi + 1e-3).reason == "teleop hold"
        late = ACFG.teleop_hold_s + 0.01
        c_lo = give(mux, lo, late)
        assert mux.decide(late + 0.01).cmd is c_lo
        assert mux.decide(late + t_lo + 1e-3).reason == "timeout"
        return
    if t_lo > t_hi:
        d = mux.decide(t_hi + 1e-3)
        assert d.cmd is c_lo and d.reason == INPUTS[lo][1] and d.deadline == pytest.approx(t_lo)
    else:
        assert mux.decide(t_hi + 1e-3).reason == "timeout"
    end = max(t_hi, t_lo) + 1e-3
    if lo == keys.TELEOP:  # stale teleop still holds the inputs below it off
        assert mux.decide(end).reason == "teleop hold"
        end = ACFG.teleop_hold_s + 1e-3
    assert mux.decide(end).reason == "timeout"


@pytest.mark.parametrize("name", ORDER[1:])
def test_each_input_alone_times_out_and_refuses_other_sources(name):
    mux = CommandMux.from_config(ACFG)
    source, reason, timeout = INPUTS[name]
    assert not mux.offer(cmd("someone-else"), name, 0.0) and mux.refused == 1
    assert mux.decide(0.0).reason == "no command"
    c = give(mux, name, 1.0)
    assert mux.decide(1.0 + timeout - 1e-3).cmd is c
    stale = "teleop hold" if name == keys.TELEOP else "timeout"
    assert mux.decide(1.0 + timeout + 1e-9).reason == stale
    c = give(mux, name, 2.0)
    mux.reject(name, 2.05)  # malformed payload on that input: dropped at once
    assert mux.decide(2.05).cmd is None and mux.malformed == 1
    assert mux.accepted_by[reason] == 2


def test_sim_mux_accepts_any_controller():
    mux = CommandMux.from_config(ACFG, controller=None, timeout_s=0.1)
    for source in ("policy", "baseline", "scripted"):
        assert mux.offer(cmd(source), keys.CMD, 0.0)
    assert mux.decide(0.05).reason == "controller" and mux.decide(0.1).reason == "timeout"
    assert not mux.offer(cmd("policy"), keys.SAFETY, 0.0)  # only the supervisor brakes


def test_safety_brake_frames():
    from racecav.common.vehicle import load_car

    m = Mapping(ACFG, load_car("slash"))
    mux = CommandMux.from_config(ACFG)
    give(mux, keys.CMD, 0.0)
    give(mux, keys.SAFETY, 0.0)
    d = mux.decide(0.0)
    assert d.brake
    frames = m.decision_frames(d)
    assert frames[0] == vp.set_current_brake(ACFG.brake_current_a)
    assert frames[1] == vp.set_servo_pos(m.servo(0.1))
    assert not mux.decide(0.21).brake and m.decision_frames(mux.decide(0.21))[0] == m.motor_frame(0.5)


def test_a_braking_command_brakes_the_motor():
    """A policy trained with a brake action (DriveCommand.brake): brake current, its steering."""
    from racecav.common.vehicle import load_car
    from racecav.services.controller import make_command
    from racecav.common.messages import Scan

    m = Mapping(ACFG, load_car("slash"))
    mux = CommandMux.from_config(ACFG)
    scan = Scan(stamp_ns=10, seq=3, angle_min=0.0, angle_max=0.0, angle_increment=0.01, ranges=[1.0],
                range_min=0.1, range_max=16.0, source="sim")
    for a_t, brakes in ((-0.9, True), (-0.3, False), (0.4, False)):
        c = make_command("policy", a_t, 0.2, load_car("slash"), scan, 0, 0, brake_below=-0.5)
        assert c.brake is brakes and (c.throttle == 0.0 if a_t <= 0 else c.throttle == 0.4)
        assert mux.offer(c, keys.CMD, 0.0)
        d = mux.decide(0.0)
        assert d.reason == "controller" and d.brake is brakes
        motor = m.decision_frames(d)[0]
        assert (motor == vp.set_current_brake(ACFG.brake_current_a)) is brakes
    # without a brake action (the paper's policies) a_T -1 coasts
    assert not make_command("policy", -1.0, 0.0, load_car("slash"), scan, 0, 0).brake


def test_forget_drops_inputs_but_not_the_estop():
    mux = CommandMux.from_config(ACFG)
    give(mux, keys.SAFETY, 0.0)
    give(mux, keys.TELEOP, 0.0)
    mux.forget()  # the sim's new episode
    assert mux.decide(0.0).reason == "no command"
    c = give(mux, keys.CMD, 0.1)  # no teleop hold survives the reset either
    assert mux.decide(0.1).cmd is c
    mux.estop(b"stop")
    mux.forget()
    assert mux.decide(0.2).reason == "estop"
