"""RPLIDAR S2 driver over pyserial: start-up handshake, scan loop, recovery. Never exits on its own.

Start-up follows the Slamtec SDK: RESET, wait what the protocol documents (2 ms: Slamtec's
"RPLIDAR Interface Protocol and Application Notes", section "Core Reset (RESET) Request",
Fig. 4-3: "host systems should wait for at least 2 milliseconds (ms) before sending another
request"), then GET_INFO every ``reset_poll_s`` until the rebooted core answers (at most
``reset_timeout_s``; requests sent while it boots are dropped, and the banner it prints is
skipped), GET_HEALTH (an error state gets one more RESET), GET_LIDAR_CONF for the mode count, the typical
mode and the chosen mode's answer type and sample period, motor speed (A8), a pause for the
motor to spin up, then SCAN (answer type 81) or EXPRESS_SCAN with the mode id (82/85).

Recovery: a stream of bytes none of which decode for ``data_timeout_s``, no bytes at all for
``silence_timeout_s`` (a stopped device: protection stop, health error), or a health error =>
RESET and start again on the same port; the port failing (USB unplugged: reads
raise, the device node disappears) => close, and retry opening every ``reconnect_s`` until it is
back. A re-opened port (not the first start) skips the RESET and its boot (a re-plugged
device has just powered up and is idle): STOP, a short settle, flush, then the handshake; if the device does not
answer properly, the next attempt does the full RESET. That is what brings the first scan within
~1 s of a replug (measured: docs/reliability.md). Statistics are counted, never raised.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import serial

from racecav.services.sensor import rplidar_protocol as rp

log = logging.getLogger("racecav.sensor.rplidar")


FRESH_SETTLE_S = 0.05
"""s between STOP and the flush on a freshly opened port (the SDK waits 1 ms after STOP)."""


def stream_garbage(stats: "DriverStats") -> int:
    """Bytes the scan parser skipped so far (resynchronisation)."""
    return int(stats.parser.as_dict().get("resync_bytes", 0))


class DeviceError(Exception):
    """The device answered wrongly or reported an error; the driver resets it."""


@dataclass
class DriverStats:
    connects: int = 0
    """Successful opens of the port (1 + reconnections)."""
    disconnects: int = 0
    """Times the port failed (unplugged) and was closed."""
    restarts: int = 0
    """RESET + restart of the scan after a device error or a data timeout."""
    revolutions: int = 0
    bytes_read: int = 0
    last_error: str = ""
    parser: rp.ParserStats = field(default_factory=rp.ParserStats)

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "parser"}
        d.update({f"parser_{k}": v for k, v in self.parser.as_dict().items()})
        return d


class RplidarDriver:
    """Reads revolutions from an RPLIDAR and hands each to ``on_revolution``.

    :param port: serial device (e.g. /dev/rplidar, a udev symlink).
    :param on_revolution: called from the driver's thread with each :class:`rp.Revolution`.
    :param baudrate: 1,000,000 for the S2.
    :param scan_mode: mode id, or None for the device's typical mode (DenseBoost on the S2).
    :param motor_rpm: motor speed sent with A8 (600 rpm = 10 Hz); 0 = do not send A8.
    :param cut_deg: device angle where revolutions are cut (see :class:`rp.RevolutionAssembler`).
    :param reset_wait_s: pause after RESET before the first GET_INFO (Slamtec's protocol: >= 2 ms).
    :param reset_poll_s: period of GET_INFO while the device boots after RESET.
    :param reset_timeout_s: give up on a device that does not answer GET_INFO for this long.
    :param spinup_s: pause between motor start and SCAN (some S2 firmware needs it).
    :param data_timeout_s: bytes but no decoded samples for this long => reset and restart the scan.
    :param silence_timeout_s: no bytes at all for this long while scanning => ask the health, reset.
    :param reconnect_s: delay between attempts to reopen a vanished port.
    :param reply_timeout_s: how long to wait for a response descriptor.
    """

    def __init__(self, port: str, on_revolution: Callable[[rp.Revolution], None], baudrate: int = 1_000_000,
                 scan_mode: int | None = None, motor_rpm: int = 600, cut_deg: float = 0.0,
                 reset_wait_s: float = 0.002, spinup_s: float = 0.5, data_timeout_s: float = 1.0,
                 reconnect_s: float = 0.1, reply_timeout_s: float = 1.0,
                 stop_event: threading.Event | None = None, reset_poll_s: float = 0.05,
                 reset_timeout_s: float = 2.0, silence_timeout_s: float = 0.3):
        self.port, self.on_revolution, self.baudrate = port, on_revolution, baudrate
        self.scan_mode, self.motor_rpm, self.cut_deg = scan_mode, motor_rpm, cut_deg
        self.reset_wait_s, self.spinup_s, self.data_timeout_s = reset_wait_s, spinup_s, data_timeout_s
        self.reconnect_s, self.reply_timeout_s = reconnect_s, reply_timeout_s
        self.reset_poll_s, self.reset_timeout_s = reset_poll_s, reset_timeout_s
        self.silence_timeout_s = silence_timeout_s
        self.stop_event = stop_event or threading.Event()
        self.stats = DriverStats()
        self.state = "idle"
        self.info: rp.DeviceInfo | None = None
        self.health: rp.Health | None = None
        self.mode_count = 0
        self.typical_mode = 0
        self.mode = 0
        self.mode_name = ""
        self.answer_type = 0
        self.us_per_sample = 0.0
        self._ser: serial.Serial | None = None
        self._fresh = False
        """The port was just opened: try the handshake without a RESET first."""
        self._just_reset = False

    # --- public ----------------------------------------------------------------------------

    def run(self) -> None:
        """Connect, scan, recover; returns only when ``stop_event`` is set."""
        while not self.stop_event.is_set():
            try:
                self._open()
            except (serial.SerialException, OSError) as e:
                self._set_state("waiting for device", f"open {self.port}: {e}")
                self.stop_event.wait(self.reconnect_s)
                continue
            try:
                while not self.stop_event.is_set():
                    try:
                        self._session()
                    except (DeviceError, rp.ProtocolError) as e:
                        # The error first: a reader that sees the count also sees its cause.
                        self._set_state("restarting", f"device error: {e}")
                        self.stats.restarts += 1
            except (serial.SerialException, OSError) as e:
                self._set_state("disconnected", f"port {self.port} failed: {e}")
                self.stats.disconnects += 1
            finally:
                self._close()
        self.state = "stopped"

    def start_thread(self) -> threading.Thread:
        t = threading.Thread(target=self.run, name="rplidar-driver", daemon=True)
        t.start()
        return t

    def status(self) -> dict:
        """JSON-able state for the service's status."""
        return dict(state=self.state, port=self.port, mode=self.mode, mode_name=self.mode_name,
                    answer_type=f"{self.answer_type:#04x}", us_per_sample=self.us_per_sample,
                    model=f"{self.info.model:#04x}" if self.info else None,
                    firmware=".".join(map(str, self.info.firmware)) if self.info else None,
                    serial=self.info.serial if self.info else None,
                    health=self.health.status if self.health else None, **self.stats.as_dict())

    # --- connection ------------------------------------------------------------------------

    def _set_state(self, state: str, error: str = "") -> None:
        if error:
            if error != self.stats.last_error:  # a vanished port retries every 0.5 s: say it once
                log.warning("%s", error)
            self.stats.last_error = error
        if state != self.state:
            log.info("rplidar: %s", state)
        self.state = state

    def _open(self) -> None:
        self._ser = serial.Serial(self.port, self.baudrate, timeout=0.05, write_timeout=1.0)
        try:
            self._ser.dtr = False  # CP210x: DTR low keeps the A-series motor running; a pty refuses it
        except (OSError, serial.SerialException):
            pass
        self.stats.connects += 1
        self._fresh = self.stats.connects > 1  # a re-plug; the first start follows the SDK (RESET)
        self._set_state("connected")

    def _close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is None:
            return
        try:
            if ser.is_open:
                ser.write(rp.request(rp.CMD_STOP))
                if self.motor_rpm:
                    ser.write(rp.motor_speed_request(0))
        except (serial.SerialException, OSError):
            pass
        try:
            ser.close()
        except (serial.SerialException, OSError):
            pass

    # --- request/response ------------------------------------------------------------------

    def _read_exact(self, n: int, deadline: float) -> bytes:
        out = bytearray()
        while len(out) < n:
            if time.monotonic() > deadline:
                raise DeviceError(f"timeout reading {n} bytes (got {len(out)})")
            chunk = self._ser.read(n - len(out))
            self.stats.bytes_read += len(chunk)
            out += chunk
        return bytes(out)

    def _read_descriptor(self, deadline: float) -> rp.Descriptor:
        """Skip bytes until ``A5 5A`` and return the descriptor after it."""
        prev = 0
        while True:
            b = self._read_exact(1, deadline)[0]
            if prev == rp.SYNC and b == rp.SYNC2:
                return rp.Descriptor.parse(bytes((rp.SYNC, rp.SYNC2)) + self._read_exact(5, deadline))
            prev = b

    def _command(self, req: bytes, dtype: int | None) -> bytes:
        """Send a request; if ``dtype`` is given, read its single response and return the data."""
        self._ser.write(req)
        if dtype is None:
            return b""
        deadline = time.monotonic() + self.reply_timeout_s
        desc = self._read_descriptor(deadline)
        if desc.dtype == rp.ANS_INFO and dtype != rp.ANS_INFO:
            # a late answer to an earlier GET_INFO of the boot poll (_reset): skip it
            self._read_exact(desc.length, deadline)
            desc = self._read_descriptor(deadline)
        if desc.dtype != dtype:
            raise DeviceError(f"request {req[:2].hex()}: answer type {desc.dtype:#x}, expected {dtype:#x}")
        return self._read_exact(desc.length, deadline)

    def _conf(self, conf_type: int, mode: int | None = None) -> bytes:
        return rp.parse_conf_answer(conf_type, self._command(rp.conf_request(conf_type, mode), rp.ANS_CONF))

    def _reset(self) -> None:
        """RESET, then GET_INFO until the rebooted core answers (sets ``info``). The protocol's
        wait after RESET is 2 ms (module docstring); how long the core then boots is the
        device's (the S2: about 2 s; the emulator: ``--reset-s``), so it is polled, not assumed."""
        self._ser.write(rp.request(rp.CMD_STOP))
        self._ser.write(rp.request(rp.CMD_RESET))
        if self.stop_event.wait(self.reset_wait_s):
            return
        deadline = time.monotonic() + self.reset_timeout_s
        while not self.stop_event.is_set():
            self._ser.reset_input_buffer()  # scan data still in flight, the boot banner
            self._ser.write(rp.request(rp.CMD_GET_INFO))
            try:
                desc = self._read_descriptor(min(deadline, time.monotonic() + self.reset_poll_s))
                if desc.dtype == rp.ANS_INFO:
                    self.info = rp.DeviceInfo.parse(self._read_exact(desc.length, time.monotonic() + self.reply_timeout_s))
                    return
            except DeviceError:  # still booting: no answer within the poll period
                pass
            if time.monotonic() >= deadline:
                raise DeviceError(f"no answer to GET_INFO within {self.reset_timeout_s:.1f} s of RESET")

    # --- one session: handshake then scan until an error -------------------------------------

    def _session(self) -> None:
        if self._fresh:  # just plugged in: idle after power-up, no RESET needed (module docstring)
            self._fresh = False
            self._set_state("handshake")
            self._ser.write(rp.request(rp.CMD_STOP))
            if self.stop_event.wait(FRESH_SETTLE_S):
                return
            self._ser.reset_input_buffer()
        else:
            self._set_state("resetting")
            self._reset()
            self._just_reset = True
        if self.stop_event.is_set():
            return
        if self._just_reset:  # _reset's poll has the info already
            self._just_reset = False
        else:
            self.info = rp.DeviceInfo.parse(self._command(rp.request(rp.CMD_GET_INFO), rp.ANS_INFO))
        self.health = rp.Health.parse(self._command(rp.request(rp.CMD_GET_HEALTH), rp.ANS_HEALTH))
        if self.health.status == rp.HEALTH_ERROR:
            raise DeviceError(f"health error code {self.health.error_code:#06x}")
        self._choose_mode()
        log.info("rplidar model %#04x fw %s serial %s health %d mode %d %s (%#04x, %.1f us/sample)",
                 self.info.model, ".".join(map(str, self.info.firmware)), self.info.serial,
                 self.health.status, self.mode, self.mode_name, self.answer_type, self.us_per_sample)
        if self.motor_rpm:
            self._command(rp.motor_speed_request(self.motor_rpm), None)
            if self.stop_event.wait(self.spinup_s):
                return
        if self.answer_type == rp.ANS_STANDARD:
            req = rp.request(rp.CMD_SCAN)
        else:
            req = rp.express_scan_request(self.mode)
        self._ser.write(req)
        desc = self._read_descriptor(time.monotonic() + self.reply_timeout_s)
        if desc.dtype != self.answer_type or desc.mode != rp.MODE_MULTI:
            raise DeviceError(f"scan answered type {desc.dtype:#x} mode {desc.mode}, expected {self.answer_type:#x}")
        self._scan_loop()

    def _choose_mode(self) -> None:
        (self.mode_count,) = struct.unpack("<H", self._conf(rp.CONF_SCAN_MODE_COUNT)[:2])
        (self.typical_mode,) = struct.unpack("<H", self._conf(rp.CONF_SCAN_MODE_TYPICAL)[:2])
        self.mode = self.typical_mode if self.scan_mode is None else self.scan_mode
        if not 0 <= self.mode < self.mode_count:
            raise DeviceError(f"scan mode {self.mode} not offered (device has {self.mode_count})")
        ans = self._conf(rp.CONF_SCAN_MODE_ANS_TYPE, self.mode)
        if not ans:
            raise DeviceError(f"no answer type for mode {self.mode}")
        self.answer_type = ans[0]
        us = self._conf(rp.CONF_SCAN_MODE_US_PER_SAMPLE, self.mode)
        self.us_per_sample = struct.unpack("<I", us[:4])[0] / 256.0 if len(us) >= 4 else 0.0
        self.mode_name = self._conf(rp.CONF_SCAN_MODE_NAME, self.mode).split(b"\0")[0].decode("ascii", "replace")
        if self.answer_type not in (rp.ANS_STANDARD, rp.ANS_EXPRESS, rp.ANS_DENSE):
            raise DeviceError(f"mode {self.mode} ({self.mode_name}) answers {self.answer_type:#x}: unsupported")

    def _scan_loop(self) -> None:
        stream = rp.ScanStream(self.answer_type, stats=self.stats.parser)
        revs = rp.RevolutionAssembler(self.cut_deg)
        self._set_state("scanning")
        last_data = time.monotonic()
        while not self.stop_event.is_set():
            n = self._ser.in_waiting
            if n < 4 * rp.CAPSULE_LEN:
                # Let a few capsules accumulate: one read per ~4 ms instead of one per capsule
                # (about 3x less CPU at 800 capsules/s for at most 4 ms more latency).
                time.sleep(0.004)
                n = self._ser.in_waiting
            chunk = self._ser.read(n if n else 1)  # blocks up to the port timeout when idle
            now = time.monotonic()
            if chunk:
                self.stats.bytes_read += len(chunk)
                samples = stream.feed(chunk)
                if not len(samples.angle_deg) and now - last_data > self.data_timeout_s:
                    # bytes keep coming but none decode (a confused device, a wrong baud rate)
                    raise DeviceError(f"no decodable scan data for {self.data_timeout_s:.1f} s "
                                      f"({stream_garbage(self.stats)} bytes skipped)")
                if len(samples.angle_deg):
                    last_data = now
                    for rev in revs.add(samples, now):
                        self.stats.revolutions += 1
                        try:
                            self.on_revolution(rev)
                        except Exception as e:  # a consumer bug must not kill the driver
                            self.stats.last_error = f"on_revolution: {e}"
                            log.exception("on_revolution failed")
            elif now - last_data > self.silence_timeout_s:
                # Silence: the device stopped (protection stop, brown-out). Ask why, then reset.
                # A scanning S2 sends ~67 kB/s without a pause: 0.3 s of nothing is no hiccup.
                try:
                    self.health = rp.Health.parse(self._command(rp.request(rp.CMD_GET_HEALTH), rp.ANS_HEALTH))
                    why = f"health {self.health.status} code {self.health.error_code:#06x}"
                except DeviceError as e:
                    why = str(e)
                raise DeviceError(f"no scan data for {self.silence_timeout_s:.1f} s ({why})")
