"""VESC: frames equal to the reference vectors, calibration, mux/watchdog, and the real actuator
service on a real router driving the VESC emulator over a pty."""

from __future__ import annotations

import json
import math
import time

import pytest

from racecav.common import keys, procs
from racecav.common.client import get_status
from racecav.common.codec import encode
from racecav.common.config import ActuatorConfig
from racecav.common.messages import DriveCommand
from racecav.common.vehicle import load_car
from racecav.services.actuator import vesc_protocol as vp
from racecav.services.actuator.control import CommandMux, Mapping, sim_steady_speed
from racecav.services.actuator.emulator import VescEmulator

H = bytes.fromhex
CAR = "car0"


# --- byte-exact vectors (shared/reference/hardware-protocols.md) ------------------------------

def test_crc_and_frame_vectors():
    assert vp.crc16(b"123456789") == 0x31C3
    assert vp.get_values() == H("02 01 04 40 84 03")
    assert vp.fw_version() == H("02 01 00 00 00 03")
    assert vp.alive() == H("02 01 1E F3 FF 03")
    assert vp.set_servo_pos(0.5) == H("02 03 0C 01 F4 E9 CB 03")
    assert vp.set_rpm(0) == H("02 05 08 00 00 00 00 02 2D 03")
    assert vp.set_duty(0.1) == H("02 05 05 00 00 27 10 AE 17 03")
    assert vp.set_current_brake(20) == H("02 05 07 00 00 4E 20 6D 75 03")


def test_frame_parser_resyncs_and_handles_long_frames():
    long_payload = bytes([vp.COMM_FW_VERSION]) + bytes(range(256)) * 2
    bad = bytearray(vp.set_rpm(1234))
    bad[-2] ^= 0xFF  # CRC broken
    stream = b"\x55\x02\x03" + vp.set_rpm(-3000) + bytes(bad) + vp.frame(long_payload) + vp.set_servo_pos(0.25)
    p = vp.FrameParser()
    got = []
    for i in range(0, len(stream), 7):  # arbitrary read sizes
        got += p.feed(stream[i:i + 7])
    cmds = [vp.parse_command(x) for x in got]
    assert [(c.name, c.value) for c in cmds] == [("SET_RPM", -3000), ("FW_VERSION", None), ("SET_SERVO_POS", 0.25)]
    assert got[1] == long_payload and p.errors >= 3


def test_get_values_parsed_defensively_by_length():
    vals = dict(temp_fet=40.5, temp_motor=33.1, avg_motor_current=-2.25, avg_input_current=1.5, duty=0.123,
                rpm=-4567, v_in=12.3, amp_hours=0.0123, watt_hours=0.5, tachometer=-99, tachometer_abs=99, fault=3)
    payload = vp.encode_values(vals)
    assert len(payload) == vp.VALUES_LEN == 74  # current firmware: the full field list
    full = vp.parse_values(payload)
    for k, v in vals.items():
        assert full[k] == pytest.approx(v)
    short = vp.parse_values(payload[:29])  # an older firmware's shorter reply
    assert set(short) == {"temp_fet", "temp_motor", "avg_motor_current", "avg_input_current", "avg_id", "avg_iq",
                          "duty", "rpm", "v_in"}
    assert vp.parse_values(payload + b"\x00" * 20)["fault"] == 3  # newer firmware: extra fields ignored
    with pytest.raises(vp.FrameError, match="expected 04"):
        vp.parse_values(b"\x05\x00")


# --- calibration and mux ----------------------------------------------------------------------

def test_xtenth_calibration_mapping():
    cfg = ActuatorConfig()
    car = load_car("slash")
    m = Mapping(cfg, car)
    assert m.servo(0.0) == pytest.approx(0.5304)
    assert m.servo(car.delta_max) == pytest.approx(0.15, abs=2e-3)  # left limit meets the servo clip
    assert m.servo(car.delta_min) == pytest.approx(0.85, abs=2e-3)
    assert m.servo(1.0) == 0.15 and m.servo(-1.0) == 0.85
    # T -> speed: the simulator's steady state (agent scale), 2.7 m/s at full throttle for the slash.
    assert sim_steady_speed(1.0, car) == pytest.approx(car.v_max * car.agent_speed_scale)
    assert m.erpm(1.0) == pytest.approx(4614 * car.v_max * car.agent_speed_scale)
    assert m.erpm(0.0) == 0 and 0 < m.erpm(0.3) < m.erpm(0.6)
    lin = Mapping(ActuatorConfig(throttle_map="linear", speed_max_mps=10.0))
    assert lin.erpm(1.0) == 23250 and lin.erpm(0.5) == pytest.approx(4614 * 5.0)  # clipped at erpm_max
    assert m.neutral_frames() == [H("02 05 07 00 00 4E 20 6D 75 03"), vp.set_servo_pos(0.5304)]
    assert Mapping(ActuatorConfig(speed_mode="duty")).motor_frame(0.5) == vp.set_duty(0.1)


def cmd(source="policy", throttle=0.5, steer=0.1, seq=0) -> DriveCommand:
    return DriveCommand(stamp_ns=time.monotonic_ns(), seq=seq, source=source, a_throttle=throttle,
                        a_steer=steer, throttle=throttle, steering_angle=steer)


def test_mux_priority_watchdog_and_estop():
    mux = CommandMux("policy", "teleop", timeout_s=0.1, teleop_hold_s=0.5)
    assert mux.decide(0.0).reason == "no command"
    assert not mux.offer(cmd("baseline"), "cmd", 0.0) and mux.refused == 1
    assert not mux.offer(cmd("policy"), "teleop", 0.0)  # the controller cannot pose as teleop
    c = cmd()
    assert mux.offer(c, "cmd", 1.0)
    d = mux.decide(1.05)
    assert d.cmd is c and d.reason == "controller" and d.deadline == pytest.approx(1.1)
    assert mux.decide(1.1).reason == "timeout"
    t = cmd("teleop", 0.2)
    mux.offer(c, "cmd", 2.0)
    mux.offer(t, "teleop", 2.0)
    assert mux.decide(2.01).cmd is t
    mux.offer(c, "cmd", 2.2)
    assert mux.decide(2.2).reason == "teleop hold"  # teleop gone stale, controller still held off
    mux.offer(c, "cmd", 2.55)
    assert mux.decide(2.56).cmd is c
    mux.reject("cmd", 2.57)
    assert mux.decide(2.57).cmd is None  # malformed: the command in force is dropped at once
    mux.estop(b"stop!")
    mux.offer(c, "cmd", 3.0)
    assert mux.decide(3.0).reason == "estop" and mux.decide(100.0).reason == "estop"  # latched
    mux.estop(b"clear")
    mux.offer(c, "cmd", 101.0)
    assert mux.decide(101.0).cmd is c


# --- the actuator service on a real router, the emulator on a pty --------------------------------

@pytest.fixture
def vesc(tmp_path):
    emu = VescEmulator(link=tmp_path / "vesc", log_path=tmp_path / "vesc.jsonl").start()
    yield emu
    emu.stop()


def wait_until(pred, timeout=10.0, step=0.01):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return False


def start_actuator(spawn, session, vesc, **env):
    env.setdefault("timeout_s", 0.1)  # the 100 ms watchdog, timed below
    env = {f"RACECAV_ACTUATOR__{k.upper()}": str(v) for k, v in env.items()}
    p = spawn("actuator", "--port", vesc.path, env=env)
    procs.wait_alive(session, CAR, "actuator", proc=p)
    assert wait_until(lambda: vesc.frames("SET_CURRENT_BRAKE"))  # neutral from the start
    return p


def publish_for(pub, seconds, rate_hz=50.0, **kw):
    end = time.monotonic() + seconds
    seq = 0
    while time.monotonic() < end:
        pub.put(encode(cmd(seq=seq, **kw)))
        seq += 1
        time.sleep(1.0 / rate_hz)


def neutral_after(vesc, t):
    return [r for r in vesc.frames("SET_CURRENT_BRAKE") if r.t > t]


def test_commands_arrive_and_watchdog_neutralises(spawn, session, vesc, tmp_path):
    p = start_actuator(spawn, session, vesc)
    pub = session.declare_publisher(keys.topic(CAR, keys.CMD), express=True)
    car, cfg = load_car("slash"), ActuatorConfig()
    m = Mapping(cfg, car)
    publish_for(pub, 0.5, throttle=0.5, steer=0.1)
    rpm = [r for r in vesc.frames("SET_RPM")]
    assert rpm and rpm[-1].value == round(m.erpm(0.5))
    assert vesc.frames("SET_SERVO_POS")[-1].value == pytest.approx(m.servo(0.1), abs=1e-3)
    # The controller dies after one last, recognisable command.
    last = cmd(throttle=0.77, steer=-0.2)
    pub.put(encode(last))
    time.sleep(0.4)
    t_last = next(r.t for r in vesc.frames("SET_RPM") if r.value == round(m.erpm(0.77)))
    stops = neutral_after(vesc, t_last)
    assert stops, "no neutral after the last command"
    gap = stops[0].t - t_last
    print(f"watchdog: neutral {gap * 1e3:.1f} ms after the last command reached the VESC (timeout 100 ms)")
    assert 0.095 <= gap <= 0.13
    centre = [r for r in vesc.frames("SET_SERVO_POS") if r.t >= stops[0].t]
    assert centre[0].value == pytest.approx(0.530, abs=1e-3)
    # Nothing but neutral after that, and the log file has every frame too.
    assert all(r.value == 0 for r in vesc.frames("SET_RPM") if r.t > stops[0].t) or \
        not [r for r in vesc.frames("SET_RPM") if r.t > stops[0].t]
    logged = [json.loads(ln) for ln in (tmp_path / "vesc.jsonl").read_text().splitlines()]
    assert len(logged) >= len(vesc.frames()) - 5 and {"t", "name", "value", "raw"} <= set(logged[0])
    # Status: GET_VALUES polled and published; the emulated motor stopped.
    st = get_status(session, CAR, "actuator")
    assert st.info["driving"] == "timeout" and st.info["values"]["v_in"] == pytest.approx(12.2)
    assert st.info["accepted"] >= 20
    # Stopping the service leaves the car neutral.
    n = len(neutral_after(vesc, 0))
    assert procs.stop(p) == 0
    assert wait_until(lambda: len(neutral_after(vesc, 0)) > n, timeout=2)


def test_estop_latches_and_sources_are_checked(spawn, session, vesc):
    start_actuator(spawn, session, vesc)
    pub = session.declare_publisher(keys.topic(CAR, keys.CMD), express=True)
    tele = session.declare_publisher(keys.topic(CAR, keys.TELEOP), express=True)
    m = Mapping(ActuatorConfig(), load_car("slash"))
    publish_for(pub, 0.3, throttle=0.4)
    assert vesc.frames("SET_RPM")[-1].value == round(m.erpm(0.4))
    # E-stop: latched while the controller keeps commanding.
    session.put(keys.topic(CAR, keys.ESTOP), b"stop")
    time.sleep(0.1)
    t_stop = time.monotonic()
    publish_for(pub, 0.4, throttle=0.4)
    assert not [r for r in vesc.frames("SET_RPM") if r.t > t_stop]
    assert len(neutral_after(vesc, t_stop)) >= 10
    assert get_status(session, CAR, "actuator").info["estop"] is True
    session.put(keys.topic(CAR, keys.ESTOP), b"clear")
    time.sleep(0.1)
    t_clear = time.monotonic()
    publish_for(pub, 0.2, throttle=0.4)
    assert [r for r in vesc.frames("SET_RPM") if r.t > t_clear]
    # A source that is not the configured controller is refused.
    time.sleep(0.3)
    t0 = time.monotonic()
    publish_for(pub, 0.3, source="baseline", throttle=0.9)
    assert not [r for r in vesc.frames("SET_RPM") if r.t > t0]
    assert get_status(session, CAR, "actuator").info["refused"] >= 5
    # Teleop overrides the controller.
    t1 = time.monotonic()
    for k in range(15):
        pub.put(encode(cmd(throttle=0.4, seq=k)))
        tele.put(encode(cmd("teleop", throttle=0.1, steer=0.0, seq=k)))
        time.sleep(0.02)
    after = [r.value for r in vesc.frames("SET_RPM") if r.t > t1 + 0.05]
    assert after and set(after) == {round(m.erpm(0.1))}
    # A malformed command neutralises at once (not after the timeout).
    time.sleep(0.6)
    publish_for(pub, 0.2, throttle=0.4)
    t2 = time.monotonic()
    pub.put(b"\x93garbage")
    assert wait_until(lambda: neutral_after(vesc, t2), timeout=1)
    assert neutral_after(vesc, t2)[0].t - t2 < 0.05


def test_actuator_reconnects_when_the_vesc_comes_back(spawn, session, tmp_path):
    link = tmp_path / "vesc"
    first = VescEmulator(link=link).start()
    try:
        start_actuator(spawn, session, first)
    finally:
        first.stop()  # USB unplugged: the pty closes and the symlink disappears
    time.sleep(0.5)
    assert get_status(session, CAR, "actuator").info["connected"] is False
    second = VescEmulator(link=link).start()
    try:
        pub = session.declare_publisher(keys.topic(CAR, keys.CMD), express=True)
        assert wait_until(lambda: (publish_for(pub, 0.1, throttle=0.3), second.frames("SET_RPM"))[1], timeout=10)
        assert get_status(session, CAR, "actuator").info["connected"] is True
    finally:
        second.stop()
