"""VESC emulator on a pseudo-terminal (`racecav emulate vesc`).

Parses the frames it is sent exactly like a VESC (CRC-checked, garbage skipped), records every
one with its arrival time (monotonic) in memory and optionally in a JSON-lines log, answers
GET_VALUES (current firmware's full field list, 74 bytes) and FW_VERSION, and runs a simple
motor model so the values move: ERPM follows the commanded ERPM (SET_RPM) or duty x
``erpm_per_duty`` (SET_DUTY) with a first-order lag, brakes decay fast, currents accelerate; like
the firmware, with no command for ``app_timeout_s`` the motor is released (coasts) and the
status field's timeout bit is set.
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import math
import os
import pty
import select
import sys
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

from racecav.services.actuator import vesc_protocol as vp

log = logging.getLogger("racecav.emulate.vesc")


@dataclass
class Record:
    t: float
    """Monotonic arrival time (s)."""
    name: str
    value: float | None
    raw: str


class VescEmulator:
    """A VESC on a pty. ``start()`` runs it in a thread; ``path`` is what the actuator opens.

    :param link: symlink to create to the pty's slave (like /dev/vesc); None = none.
    :param log_path: JSON-lines file receiving one record per frame received.
    :param tau_s: motor response time constant.
    :param app_timeout_s: firmware timeout after which the motor is released.
    """

    def __init__(self, link: str | Path | None = None, log_path: str | Path | None = None, tau_s: float = 0.15,
                 app_timeout_s: float = 1.0, erpm_per_duty: float = 60000.0, v_in: float = 12.2):
        self.link = Path(link) if link else None
        self.log_path = Path(log_path) if log_path else None
        self.tau_s, self.app_timeout_s, self.erpm_per_duty, self.v_in = tau_s, app_timeout_s, erpm_per_duty, v_in
        self.records: list[Record] = []
        self.parser = vp.FrameParser()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self._log = None
        self.slave_name = ""
        # motor model state
        self.mode = "released"
        self.target = 0.0
        self.rpm = 0.0
        self.servo = 0.5
        self.tacho = 0.0
        self.current = 0.0
        self.fault = 0
        self._last_cmd = 0.0
        self._last_t = time.monotonic()

    @property
    def path(self) -> str:
        return str(self.link) if self.link else self.slave_name

    def start(self) -> "VescEmulator":
        self._master, self._slave = pty.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.slave_name = os.ttyname(self._slave)
        if self.link:
            tmp = self.link.with_name(self.link.name + ".tmp")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(self.slave_name)
            tmp.replace(self.link)
        if self.log_path:
            self._log = open(self.log_path, "a", buffering=1)
        self._thread = threading.Thread(target=self._loop, name="vesc-emulator", daemon=True)
        self._thread.start()
        log.info("vesc emulator on %s%s", self.slave_name, f" (link {self.link})" if self.link else "")
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread:
            self._thread.join(2.0)
        if self.link:
            self.link.unlink(missing_ok=True)
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1
        if self._log:
            self._log.close()

    def frames(self, *names: str) -> list[Record]:
        """Records received so far, optionally only those with these command names."""
        with self._lock:
            return [r for r in self.records if not names or r.name in names]

    # --- loop -------------------------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.01)
                data = os.read(self._master, 4096) if ready else b""
            except OSError as e:
                if e.errno not in (errno.EIO, errno.EAGAIN):
                    raise
                data = b""
                time.sleep(0.005)
            now = time.monotonic()
            for payload in self.parser.feed(data) if data else ():
                self._on_payload(payload, now)
            self._model(now)

    def _on_payload(self, payload: bytes, now: float) -> None:
        try:
            c = vp.parse_command(payload)
        except vp.FrameError:
            self.parser.errors += 1
            return
        rec = Record(now, c.name, c.value, payload.hex())
        with self._lock:
            self.records.append(rec)
        if self._log:
            self._log.write(json.dumps(rec.__dict__) + "\n")
        if c.cmd == vp.COMM_GET_VALUES:
            self._write(vp.frame(vp.encode_values(self.values())))
        elif c.cmd == vp.COMM_FW_VERSION:
            self._write(vp.frame(bytes((vp.COMM_FW_VERSION, 6, 2)) + b"racecav-emulator\0"))
        elif c.cmd == vp.COMM_SET_SERVO_POS:
            self.servo = min(max(c.value, 0.0), 1.0)
        elif c.cmd in (vp.COMM_SET_RPM, vp.COMM_SET_DUTY, vp.COMM_SET_CURRENT, vp.COMM_SET_CURRENT_BRAKE):
            self.mode, self.target, self._last_cmd = c.name, c.value, now
        elif c.cmd == vp.COMM_ALIVE:
            self._last_cmd = now

    def _write(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except OSError:
            pass  # nobody reads: dropped like a full USB buffer

    def _model(self, now: float) -> None:
        dt, self._last_t = now - self._last_t, now
        if self.mode != "released" and now - self._last_cmd > self.app_timeout_s:
            self.mode = "released"  # the firmware's own timeout: a backstop only
        a = 1.0 - math.exp(-dt / self.tau_s)
        if self.mode == "SET_RPM":
            target, self.current = self.target, (self.target - self.rpm) * 1e-3
        elif self.mode == "SET_DUTY":
            target, self.current = self.target * self.erpm_per_duty, self.target * 20.0
        elif self.mode == "SET_CURRENT":
            target, self.current = self.rpm + self.target * 2000.0 * dt / max(a, 1e-9), self.target
        elif self.mode == "SET_CURRENT_BRAKE":
            target, self.current = 0.0, -abs(self.target)
            a = min(1.0, a * 3.0)  # braking stops faster than the drive accelerates
        else:
            target, self.current, a = 0.0, 0.0, 1.0 - math.exp(-dt / 2.0)  # coasting
        self.rpm += a * (target - self.rpm)
        self.tacho += self.rpm * dt / 60.0 * 6  # 6 tacho steps per electrical revolution (3 phases x 2)

    def values(self) -> dict[str, float]:
        """The GET_VALUES fields (all of current firmware's, see vesc_protocol.VALUES_FIELDS)."""
        timed_out = time.monotonic() - self._last_cmd > self.app_timeout_s
        duty = self.rpm / self.erpm_per_duty
        return dict(temp_fet=31.5, temp_motor=29.0, avg_motor_current=self.current,
                    avg_input_current=self.current * abs(duty), avg_id=0.0, avg_iq=self.current, duty=duty,
                    rpm=self.rpm, v_in=self.v_in, tachometer=self.tacho, tachometer_abs=abs(self.tacho),
                    fault=self.fault, pid_pos=0.0, controller_id=0,
                    temp_mos1=31.4, temp_mos2=31.6, temp_mos3=31.5, avg_vd=0.0, avg_vq=duty * self.v_in,
                    status=vp.STATUS_TIMEOUT if timed_out else 0)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--link", default="/tmp/racecav-vesc", help="symlink to the pty (what `racecav actuator --port` opens)")
    p.add_argument("--log", help="JSON-lines file recording every frame received (t, name, value, raw)")
    p.add_argument("--quiet", action="store_true", help="do not print the frames received")


def run(args: argparse.Namespace, cfg=None) -> int:
    emu = VescEmulator(link=args.link, log_path=args.log).start()
    print(emu.path, flush=True)
    import signal

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    seen = 0
    shown: dict[str, float | None] = {}
    try:
        while not stop.wait(0.2):
            recs = emu.frames()
            if not args.quiet:
                for r in recs[seen:]:  # changes only: the actuator repeats itself at 50 Hz
                    if r.name != "GET_VALUES" and shown.get(r.name, "") != r.value:
                        shown[r.name] = r.value
                        print(f"{r.t:.3f} {r.name} {r.value}", flush=True)
            seen = len(recs)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    return 0
