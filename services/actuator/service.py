"""`racecav actuator`: DriveCommands to the VESC, with its own watchdog (the firmware's is a backstop).

Inputs, in the mux's priority order: racecav/<car>/estop (any payload latches, "clear"
clears), .../safety (the safety supervisor's brake), .../teleop (overrides), .../drive_ros (ROS
/drive), .../cmd (the configured controller only). Every decision is in
:mod:`racecav.services.actuator.control`; this module wires it to the bus and the serial port.

E-stop across restarts (:mod:`racecav.common.estop`): the latch is written to
``<state_dir>/estop-<car>.json`` and also kept by the router; the actuator starts latched if
either says so, until exactly ``clear`` arrives. Fail-safe: the controller's liveliness token
vanishing (a dead process) drops its command at once (``follow_liveliness``); ``timeout_s``
stays the backstop for a live but silent controller.

Timing: a fresh command is forwarded as soon as it arrives; the current command (or neutral) is
re-sent at rate_hz; the loop also wakes exactly when the command in force goes stale, so the
motor is neutralised timeout_s after the last command, not up to a period later.
Status: GET_VALUES is polled at values_hz; the values are published as JSON on
racecav/<car>/vesc and included in the status queryable's info.
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import serial

from racecav.common.bus import Service
from racecav.common.codec import DecodeError, decode
from racecav.common.config import Config
from racecav.common import keys
from racecav.common.estop import LatchFile, is_clear
from racecav.common.keys import CMD, DRIVE_ROS, ESTOP, SAFETY, TELEOP
from racecav.common.messages import DriveCommand
from racecav.services.actuator import vesc_protocol as vp
from racecav.services.actuator.control import CommandMux, Decision, Mapping


class VescLink:
    """The serial port to the VESC: writes frames, reads replies in a thread, reopens on failure.

    :param on_values: called (reader thread) with each parsed GET_VALUES dict.
    """

    def __init__(self, port: str, baudrate: int, on_values, reconnect_s: float = 0.5):
        self.port, self.baudrate, self.on_values, self.reconnect_s = port, baudrate, on_values, reconnect_s
        self._ser: serial.Serial | None = None
        self._wlock = threading.Lock()
        self._stop = threading.Event()
        self.parser = vp.FrameParser()
        self.frames_sent = 0
        self.write_errors = 0
        self.connected = False
        self.last_error = ""
        self._thread = threading.Thread(target=self._read_loop, name="vesc-reader", daemon=True)
        self._thread.start()

    def _open(self) -> None:
        self._ser = serial.Serial(self.port, self.baudrate, timeout=0.05, write_timeout=0.05)
        self.connected = True

    def _drop(self, e: Exception) -> None:
        self.last_error = f"{self.port}: {e}"
        self.connected = False
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (OSError, serial.SerialException):
                pass

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            if self._ser is None:
                try:
                    with self._wlock:
                        self._open()
                except (OSError, serial.SerialException) as e:
                    self.last_error = f"open {self.port}: {e}"
                    self._stop.wait(self.reconnect_s)
                    continue
            try:
                data = self._ser.read(self._ser.in_waiting or 1)
            except (OSError, serial.SerialException, TypeError, AttributeError) as e:
                with self._wlock:
                    self._drop(e)
                continue
            for payload in self.parser.feed(data) if data else ():
                if payload[:1] == bytes((vp.COMM_GET_VALUES,)):
                    try:
                        self.on_values(vp.parse_values(payload))
                    except vp.FrameError:
                        self.parser.errors += 1

    def write(self, frames: list[bytes]) -> bool:
        """Send frames in one write (one USB transfer); False if the port is down."""
        with self._wlock:
            if self._ser is None:
                return False
            try:
                self._ser.write(b"".join(frames))
                self.frames_sent += len(frames)
                return True
            except (OSError, serial.SerialException) as e:
                self.write_errors += 1
                self._drop(e)
                return False

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        with self._wlock:
            if self._ser is not None:
                self._drop(Exception("closed"))


class ActuatorService(Service):
    def __init__(self, cfg: Config, port: str | None = None, name: str = "actuator"):
        super().__init__(cfg, name)
        self.acfg = cfg.actuator
        self.port = port or self.acfg.port
        self._wake = threading.Condition()
        self._new = False
        self.values: dict = {}
        self._values_t = 0.0
        self.decision: Decision | None = None
        self._last_reason = ""
        self._next_send = 0.0
        self._next_poll = 0.0
        self.link: VescLink | None = None
        self._serial_error = ""
        self.sim_refused = 0
        self.latch = LatchFile(self.acfg.state_dir, self.car)

    def setup(self) -> None:
        from racecav.common.vehicle import load_car

        car = load_car(self.acfg.car) if self.acfg.throttle_map == "sim" else None
        self.mapping = Mapping(self.acfg, car)
        self.mux = CommandMux.from_config(self.acfg)
        self.link = VescLink(self.port, self.acfg.baudrate, self._on_values)
        self.values_pub = self.session.declare_publisher(self.topic("vesc"))
        self._declared.append(self.values_pub)
        self.subscribe(self.topic(CMD), None, lambda raw: self._on_cmd(raw, "cmd"))
        # the mux's inputs (order and timeouts: actuator/control.py)
        for channel in (SAFETY, TELEOP, DRIVE_ROS):
            self.subscribe(self.topic(channel), None, lambda raw, c=channel: self._on_cmd(raw, c))
        self.subscribe(self.topic(ESTOP), None, self._on_estop)
        self.queryable("values", lambda _p: dict(self.values))
        self._start_latch()
        self.controller_alive: bool | None = None
        self.controller_lost = 0
        self.from_lost = 0
        """Controller commands refused because its liveliness token is gone (one in flight when
        it died must not drive again); it is accepted again when the token returns."""
        if self.acfg.follow_liveliness:
            self.watch_alive(self.acfg.controller, self._on_controller_alive)

    def _start_latch(self) -> None:
        """Start latched if the latch file or the router says so (module docstring)."""
        why = []
        rec = self.latch.load()
        if rec is not None:
            why.append(f"latch file {self.latch.path}")
        try:
            for reply in self.session.get(keys.service_key(self.car, "router", "estop"), timeout=0.5):
                if reply.ok is not None and json.loads(reply.ok.payload.to_bytes()).get("latched") is True:
                    why.append("router")
        except Exception as e:  # no racecav router (zenohd): the file is the only copy
            self.log.debug("router estop query: %s", e)
        if why:
            self.mux.estop(b"latched at start")
            self.latch.save(True, "latched at start: " + ", ".join(why))
            self.log.warning("e-stop latched at start (%s): publish exactly 'clear' on %s to drive",
                             ", ".join(why), self.topic(ESTOP))

    def _on_controller_alive(self, _name: str, alive: bool) -> None:
        self.controller_alive = alive
        self.log.info("controller %s: liveliness %s", self.acfg.controller, "up" if alive else "lost")
        if not alive:  # every withdrawal, even if its appearance was not seen
            self.controller_lost += 1
            self.mux.lost(CMD)
            self._notify()
            self._record_error(f"controller {self.acfg.controller}: liveliness lost, braking")

    # --- callbacks (Zenoh threads: short, never block) ------------------------------------------

    def _on_cmd(self, raw: bytes, channel: str) -> None:
        now = time.monotonic()
        try:
            msg = decode(raw, DriveCommand, self.cfg.bus.max_payload_bytes)
        except DecodeError as e:
            self.invalid += 1
            self._record_error(f"malformed {channel}: {e}")
            self.mux.reject(channel, now)
        else:
            if msg.scan_source == "sim" and not self.acfg.sim_scans_drive:
                self.sim_refused += 1
                self._record_error(f"refused {channel}: answers a simulator scan (actuator.sim_scans_drive is off)")
            elif channel == CMD and self.controller_alive is False and msg.source == self.acfg.controller:
                self.from_lost += 1
            elif not self.mux.offer(msg, channel, now):
                self._record_error(f"refused {channel}: source {msg.source!r}")
        self._notify()

    def _on_estop(self, raw: bytes) -> None:
        was = self.mux.estopped
        self.mux.estop(raw)
        self._notify()  # brake first, then the disk
        if self.mux.estopped != was or (self.mux.estopped and self.latch.error):
            self.latch.save(not is_clear(raw), repr(bytes(raw[:40])))
            # transitions only: a flood of e-stop payloads must not flood the log
            self._rlog.warning(f"estop {self.mux.estopped}", f"e-stop {'latched' if self.mux.estopped else 'cleared'}"
                               + (f" (latch file not written: {self.latch.error})" if self.latch.error else ""))

    def _notify(self) -> None:
        with self._wake:
            self._new = True
            self._wake.notify()

    def _on_values(self, values: dict) -> None:
        self._values_t = time.monotonic()
        values = dict(values, stamp_ns=time.monotonic_ns())
        self.values = values
        self.values_pub.put(json.dumps(values).encode())

    # --- loop -------------------------------------------------------------------------------------

    def step(self) -> None:
        if self.link.last_error and self.link.last_error != self._serial_error:
            self._record_error(f"serial: {self.link.last_error}")  # e.g. a missing port, logged once
        self._serial_error = self.link.last_error
        now = time.monotonic()
        deadline = self.decision.deadline if self.decision else now
        wake = min(self._next_send, deadline, self._next_poll if self.acfg.values_hz else now + 1.0)
        with self._wake:
            if not self._new:
                self._wake.wait(max(0.0, min(wake - now, 0.5)))
            new, self._new = self._new, False
        now = time.monotonic()
        d = self.mux.decide(now)
        changed = d.reason != self._last_reason or (d.cmd is not None and self.decision is not None
                                                   and d.cmd is not self.decision.cmd)
        if changed or now >= self._next_send:
            frames = self.mapping.decision_frames(d)
            self.link.write(frames)
            self._next_send = now + 1.0 / self.acfg.rate_hz
            if d.reason != self._last_reason:
                self.log.info("driving: %s", d.reason)
        self.decision, self._last_reason = d, d.reason
        if self.acfg.values_hz and now >= self._next_poll:
            self.link.write([vp.get_values()])
            self._next_poll = now + 1.0 / self.acfg.values_hz

    def info(self) -> dict:
        d = self.decision
        return dict(port=self.port, connected=bool(self.link and self.link.connected),
                    driving=d.reason if d else "", estop=self.mux.estopped if self.link else False,
                    accepted=self.mux.accepted if self.link else 0,
                    accepted_by=dict(self.mux.accepted_by) if self.link else {}, refused=self.mux.refused if self.link else 0,
                    malformed=self.mux.malformed if self.link else 0,
                    frames_sent=self.link.frames_sent if self.link else 0,
                    serial_error=self.link.last_error if self.link else "",
                    controller_alive=getattr(self, "controller_alive", None),
                    controller_lost=getattr(self, "controller_lost", 0), from_lost=getattr(self, "from_lost", 0),
                    latch_file=str(self.latch.path), latch_error=self.latch.error, sim_refused=self.sim_refused,
                    values=self.values, values_age_s=round(time.monotonic() - self._values_t, 3) if self._values_t else None)

    def teardown(self) -> None:
        # Stopping the service stops the car: neutral and centred, then let go of the port.
        if self.link is not None:
            self.link.write(self.mapping.neutral_frames())
            self.link.close()


def send_neutral(cfg: Config, port: str | None = None) -> int:
    """Write the neutral frames (motor per actuator.neutral, steering centred) once and return.

    The racecav-actuator unit runs this as ExecStopPost: after a clean stop it repeats what the
    teardown sent; after a crash, SIGKILL or watchdog abort (no teardown) it is what stops the car
    before the VESC's own timeout would.
    """
    port = port or cfg.actuator.port
    try:
        with serial.Serial(port, cfg.actuator.baudrate, timeout=0.1, write_timeout=0.5) as ser:
            ser.write(b"".join(Mapping(cfg.actuator).neutral_frames()))
            ser.flush()
    except (OSError, serial.SerialException) as e:
        print(f"racecav actuator --neutral: {port}: {e}")
        return 2  # a bad set-up (no such port), like every other
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", help="serial device (default: actuator.port, /dev/vesc)")
    p.add_argument("--name", default="actuator", help="service name (keys racecav/<car>/<name>/...)")
    p.add_argument("--neutral", action="store_true",
                   help="send neutral (brake, steering centred) once and exit, without joining the bus "
                        "(the unit's ExecStopPost: a crashed actuator still leaves the motor stopped)")


def run(args: argparse.Namespace, cfg: Config) -> int:
    if args.neutral:
        return send_neutral(cfg, args.port)
    return ActuatorService(cfg, port=args.port, name=args.name).run()
