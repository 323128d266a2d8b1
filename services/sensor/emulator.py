"""RPLIDAR S2 emulator on a pseudo-terminal (`racecav emulate rplidar`).

It answers the request grammar byte for byte like the device (info, health, GET_LIDAR_CONF,
motor speed, SCAN, EXPRESS_SCAN for the standard/express/dense modes, STOP, RESET) and streams
scans with valid checksums, the start flag only on the first capsule of a scan, evenly stepped
start angles, and output paced like the device: a pty has no baud rate, so the emulator sends
each capsule when the device would have finished sampling it (DenseBoost: 800 capsules/s,
about 67 kB/s at 10 Hz, within the 100 kB/s of a 1 Mbaud 8N1 link).

Express capsules (answer type 82, offered with ``modes=S2_MODES + (EXPRESS_MODE,)`` or
``--express``) carry random per-sample angle offsets, as a real device's do, at least 1 deg on
the samples just after 0 deg so that every turn tests cutting by the raw angle.

Faults for testing the driver: garbage bytes, corrupt checksums, truncated capsules, a health
error state, and unplug/replug (the pty is closed and the symlink the driver opens disappears,
then a new pty appears under the same symlink, as udev does with /dev/rplidar).

The scene is in the lidar's own REP-103 frame (x forward, y left, counter-clockwise angles);
the device reports clockwise degrees, so device angle a looks along -a.
"""

from __future__ import annotations

import argparse
import errno
import logging
import math
import os
import pty
import select
import struct
import sys
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from racecav.services.sensor import rplidar_protocol as rp

log = logging.getLogger("racecav.emulate.rplidar")


# --- scenes -------------------------------------------------------------------------------------

class WallScene:
    """Fixed walls as segments (x0, y0, x1, y1) in the lidar frame; ranges by ray casting.

    :param walls: (M, 4) segments in metres.
    :param max_range_m: beyond this (or no hit) the device reports 0 = no return.
    """

    def __init__(self, walls, max_range_m: float = 30.0):
        self.walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
        self.max_range_m = max_range_m

    def ranges_mm(self, device_deg: np.ndarray, rev: int = 0) -> np.ndarray:
        """Distances (mm, 0 = no return) along the device angles (clockwise degrees)."""
        th = -np.radians(device_deg)[:, None]
        dx, dy = np.cos(th), np.sin(th)
        x0, y0, x1, y1 = (self.walls[:, k][None, :] for k in range(4))
        ex, ey = x1 - x0, y1 - y0
        den = dx * ey - dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (x0 * ey - y0 * ex) / den  # distance along the ray
            u = (x0 * dy - y0 * dx) / den  # position along the segment
        hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
        t = np.where(hit, t, np.inf).min(axis=1)
        return np.where(t <= self.max_range_m, t * 1000.0, 0.0)


def default_walls() -> np.ndarray:
    """A 3 m wide corridor ending 6 m ahead, with a 0.3 m box 2 m ahead slightly to the left."""
    return np.array([
        [-3.0, 1.5, 6.0, 1.5], [-3.0, -1.5, 6.0, -1.5], [6.0, -1.5, 6.0, 1.5], [-3.0, -1.5, -3.0, 1.5],
        [2.0, 0.2, 2.3, 0.2], [2.3, 0.2, 2.3, 0.5], [2.3, 0.5, 2.0, 0.5], [2.0, 0.5, 2.0, 0.2],
    ])


class ReplayScene:
    """Scans replayed from an .npz file, one per revolution, cycling.

    The file holds ``ranges`` (R, N) in metres (inf or 0 = no return) over
    ``angle_min`` .. in steps of ``angle_increment`` (rad, counter-clockwise, lidar frame), e.g.
    scans recorded from the simulator. Angles outside the recorded span have no return.
    """

    def __init__(self, path: str | Path):
        with np.load(path) as z:
            try:
                self.ranges = np.atleast_2d(np.asarray(z["ranges"], dtype=np.float64))
                self.angle_min = float(z["angle_min"])
                self.angle_increment = float(z["angle_increment"])
            except KeyError as e:
                raise ValueError(f"replay file {path}: missing array {e}") from None
        if self.angle_increment <= 0 or self.ranges.shape[1] < 2:
            raise ValueError(f"replay file {path}: need angle_increment > 0 and >= 2 rays")

    def ranges_mm(self, device_deg: np.ndarray, rev: int = 0) -> np.ndarray:
        r = self.ranges[rev % len(self.ranges)]
        ccw = np.mod(-np.radians(device_deg) + math.pi, 2 * math.pi) - math.pi
        idx = np.rint((ccw - self.angle_min) / self.angle_increment).astype(np.int64)
        inside = (idx >= 0) & (idx < r.shape[0])
        out = np.where(inside, r[np.clip(idx, 0, r.shape[0] - 1)], 0.0)
        out = np.where(np.isfinite(out), out, 0.0)
        return out * 1000.0


# --- device model -------------------------------------------------------------------------------

@dataclass(frozen=True)
class ScanMode:
    name: str
    answer_type: int
    us_per_sample: float
    max_distance_m: float = 30.0


S2_MODES = (
    ScanMode("Standard", rp.ANS_STANDARD, 1e6 / 5000),  # emulator's choice of rate, not vendor data
    ScanMode("DenseBoost", rp.ANS_DENSE, 1e6 / 32000),
)
EXPRESS_MODE = ScanMode("Express", rp.ANS_EXPRESS, 1e6 / 16000)
"""Not an S2 mode (A-series): ``modes=S2_MODES + (EXPRESS_MODE,)`` lets tests cover answer type 82."""
S2_TYPICAL_MODE = 1
S2_INFO = rp.DeviceInfo(model=0x71, firmware=(1, 2), hardware=18, serial="C0FFEE00112233445566778899AABBCC")


@dataclass
class Faults:
    """Pending one-shot faults, applied to the next scan units sent."""

    garbage: list[bytes] = field(default_factory=list)
    corrupt: int = 0
    truncate: int = 0


class RplidarEmulator:
    """An RPLIDAR S2 on a pty. ``start()`` runs it in a thread; ``path`` is what a driver opens.

    :param scene: object with ``ranges_mm(device_deg, rev) -> mm``.
    :param link: symlink to create to the pty's slave (like /dev/rplidar); None = no symlink.
    :param reset_s: how long the device stays silent after RESET.
    :param garbage_every / corrupt_every / truncate_every: periodic faults every N scan units.
    :param modes: scan modes offered (GET_LIDAR_CONF), typical mode 1.
    :param express_offset_max_q3: express capsules (82) carry a random angle offset per sample
        in 0..this (q3 degrees, at most 63 = 7.875 deg; 0 = none), and the samples of the
        first capsule after 0 deg at least 1 deg, so every turn has samples whose corrected
        angle lies before the wrap (what cutting turns by the corrected angle got wrong).
    """

    def __init__(self, scene=None, link: str | Path | None = None, reset_s: float = 0.5,
                 garbage_every: int = 0, corrupt_every: int = 0, truncate_every: int = 0,
                 seed: int = 0, modes: tuple[ScanMode, ...] = S2_MODES, express_offset_max_q3: int = 63):
        self.scene = scene or WallScene(default_walls())
        self.link = Path(link) if link else None
        self.reset_s = reset_s
        self.garbage_every, self.corrupt_every, self.truncate_every = garbage_every, corrupt_every, truncate_every
        self.rng = np.random.default_rng(seed)
        self.modes = modes
        if not 0 <= express_offset_max_q3 <= 63:
            raise ValueError(f"express_offset_max_q3 {express_offset_max_q3} outside 0..63 (6 bits)")
        self.express_offset_max_q3 = express_offset_max_q3
        self.health = rp.Health(rp.HEALTH_OK, 0)
        self.rpm = 0
        self.default_rpm = 600
        self._lock = threading.Lock()
        self._faults = Faults()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self.slave_name = ""
        self._parser = rp.RequestParser()
        self._streaming: ScanMode | None = None
        self._silent_until = 0.0
        self._pending_banner = False
        self._unplug_until = 0.0
        # counters and records for tests
        self.requests: list[tuple[float, int, bytes]] = []
        self.units_sent = 0
        self.revolutions = 0
        self.dropped_bytes = 0
        self.plug_count = 0

    # --- pty -----------------------------------------------------------------------------------

    @property
    def path(self) -> str:
        """What a driver should open: the symlink if any, else the slave device."""
        return str(self.link) if self.link else self.slave_name

    def _plug(self) -> None:
        self._master, self._slave = pty.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.slave_name = os.ttyname(self._slave)
        self._parser = rp.RequestParser()
        self._streaming = None
        if self.link:
            tmp = self.link.with_name(self.link.name + ".tmp")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(self.slave_name)
            tmp.replace(self.link)  # atomic: the driver never sees a half-made link
        self.plug_count += 1
        log.info("rplidar emulator on %s%s", self.slave_name, f" (link {self.link})" if self.link else "")

    def _unplug_now(self) -> None:
        if self.link:
            self.link.unlink(missing_ok=True)
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1
        self._streaming = None

    # --- control API (thread-safe) -------------------------------------------------------------

    def start(self) -> "RplidarEmulator":
        self._plug()
        self._thread = threading.Thread(target=self._loop, name="rplidar-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread:
            self._thread.join(2.0)
        self._unplug_now()

    def inject_garbage(self, data: bytes | int) -> None:
        """Send these bytes (or this many random bytes) between two scan units."""
        with self._lock:
            if isinstance(data, int):
                data = self.rng.integers(0, 256, data, dtype=np.uint8).tobytes()
            self._faults.garbage.append(bytes(data))

    def corrupt_next(self, n: int = 1) -> None:
        """Flip one byte inside each of the next n scan units (checksum failure)."""
        with self._lock:
            self._faults.corrupt += n

    def truncate_next(self, n: int = 1) -> None:
        """Cut the tail off each of the next n scan units (lost bytes)."""
        with self._lock:
            self._faults.truncate += n

    def unplug(self, duration_s: float) -> None:
        """Disappear for duration_s (pty closed, symlink removed), then come back."""
        with self._lock:
            self._unplug_until = time.monotonic() + duration_s

    def set_health(self, status: int, code: int = 0) -> None:
        """Device health; an error stops a running scan, like the device protecting itself."""
        with self._lock:
            self.health = rp.Health(status, code)
            if status == rp.HEALTH_ERROR:
                self._streaming = None

    @property
    def streaming(self) -> bool:
        return self._streaming is not None

    # --- main loop -----------------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stop.is_set():
            if self._unplug_until:
                if self._master >= 0:
                    self._unplug_now()
                    log.info("rplidar emulator unplugged")
                if time.monotonic() < self._unplug_until:
                    time.sleep(0.01)
                    continue
                self._unplug_until = 0.0
                self._plug()
            timeout = 0.02
            if self._streaming is not None:
                timeout = max(0.0, min(timeout, self._next_due - time.monotonic()))
            try:
                ready, _, _ = select.select([self._master], [], [], timeout)
                if ready:
                    data = os.read(self._master, 4096)
                    self._on_bytes(data)
            except OSError as e:
                if e.errno not in (errno.EIO, errno.EAGAIN):
                    raise
                time.sleep(0.005)
            if self._streaming is not None:
                self._emit_due()
            if self._pending_banner and time.monotonic() >= self._silent_until:
                # After a reset the firmware prints a text banner: the driver must flush it.
                self._pending_banner = False
                self._write(b"RP S2 LIDAR System.\r\nFirmware Ver 1.02 - emulated\r\n")

    def _write(self, data: bytes) -> None:
        try:
            n = os.write(self._master, data)
        except BlockingIOError:
            n = 0
        except OSError:
            n = 0
        if n < len(data):  # nobody reads: the host's buffer overflows and bytes are lost
            self.dropped_bytes += len(data) - n

    def _on_bytes(self, data: bytes) -> None:
        now = time.monotonic()
        for req in self._parser.feed(data):
            self.requests.append((now, req.cmd, req.payload))
            if now < self._silent_until:
                continue  # booting after RESET
            self._handle(req, now)

    def _answer(self, dtype: int, payload: bytes, mode: int = rp.MODE_SINGLE) -> None:
        self._write(rp.Descriptor(len(payload), mode, dtype).encode() + payload)

    def _handle(self, req: rp.Request, now: float) -> None:
        cmd = req.cmd
        if cmd == rp.CMD_STOP:
            self._streaming = None
        elif cmd == rp.CMD_RESET:
            self._streaming = None
            self.rpm = 0
            self.health = rp.Health(rp.HEALTH_OK, 0)
            self._silent_until = now + self.reset_s
            self._pending_banner = True
        elif cmd == rp.CMD_GET_INFO:
            self._answer(rp.ANS_INFO, S2_INFO.encode())
        elif cmd == rp.CMD_GET_HEALTH:
            self._answer(rp.ANS_HEALTH, self.health.encode())
        elif cmd == rp.CMD_GET_SAMPLERATE:
            self._answer(0x15, struct.pack("<HH", int(self.modes[0].us_per_sample), int(self.modes[1].us_per_sample)))
        elif cmd == rp.CMD_GET_LIDAR_CONF:
            self._conf(req.payload)
        elif cmd == rp.CMD_MOTOR_SPEED and len(req.payload) == 2:
            (self.rpm,) = struct.unpack("<H", req.payload)
        elif cmd in (rp.CMD_SCAN, rp.CMD_FORCE_SCAN):
            self._start_scan(self.modes[0], now)
        elif cmd == rp.CMD_EXPRESS_SCAN and len(req.payload) == 5:
            mode = req.payload[0]
            if mode < len(self.modes):
                self._start_scan(self.modes[mode], now)

    def _conf(self, payload: bytes) -> None:
        if len(payload) < 4:
            return
        (ctype,) = struct.unpack_from("<I", payload)
        mode = struct.unpack_from("<H", payload, 4)[0] if len(payload) >= 6 else 0
        m = self.modes[mode] if mode < len(self.modes) else None
        if ctype == rp.CONF_SCAN_MODE_COUNT:
            data = struct.pack("<H", len(self.modes))
        elif ctype == rp.CONF_SCAN_MODE_TYPICAL:
            data = struct.pack("<H", S2_TYPICAL_MODE)
        elif m is None:
            data = b""  # the device answers an unknown mode with no data
        elif ctype == rp.CONF_SCAN_MODE_US_PER_SAMPLE:
            data = struct.pack("<I", int(m.us_per_sample * 256))
        elif ctype == rp.CONF_SCAN_MODE_MAX_DISTANCE:
            data = struct.pack("<I", int(m.max_distance_m * 256))
        elif ctype == rp.CONF_SCAN_MODE_ANS_TYPE:
            data = bytes((m.answer_type,))
        elif ctype == rp.CONF_SCAN_MODE_NAME:
            data = m.name.encode() + b"\0"
        else:
            data = b""
        self._answer(rp.ANS_CONF, struct.pack("<I", ctype) + data)

    # --- streaming -----------------------------------------------------------------------------

    def _start_scan(self, mode: ScanMode, now: float) -> None:
        if self.health.status == rp.HEALTH_ERROR:
            return  # a device in protection stop does not scan
        unit = {rp.ANS_STANDARD: rp.STANDARD_NODE_LEN}.get(mode.answer_type, rp.CAPSULE_LEN)
        self._write(rp.Descriptor(unit, rp.MODE_MULTI, mode.answer_type).encode())
        self._streaming = mode
        self._unit_index = 0
        self._sample_index = 0
        self._t0 = now + 0.002
        self._next_due = self._t0
        self._rev_cache: tuple[int, np.ndarray] | None = None

    def _samples_per_rev(self, mode: ScanMode) -> int:
        rpm = self.rpm or self.default_rpm
        return max(40, int(round(60.0 / rpm * 1e6 / mode.us_per_sample)))

    def _unit_samples(self, mode: ScanMode) -> int:
        return {rp.ANS_STANDARD: 1, rp.ANS_DENSE: rp.DENSE_SAMPLES, rp.ANS_EXPRESS: rp.EXPRESS_SAMPLES}[mode.answer_type]

    def _emit_due(self) -> None:
        mode = self._streaming
        now = time.monotonic()
        per_unit = self._unit_samples(mode)
        unit_s = per_unit * mode.us_per_sample * 1e-6
        out = bytearray()
        # Send what the device has finished sampling by now (at most 50 ms worth in one go).
        while self._next_due <= now and len(out) < 8192:
            out += self._unit(mode, per_unit)
            self._unit_index += 1
            self._next_due = self._t0 + self._unit_index * unit_s
        if self._next_due < now - 0.2:  # fell far behind (machine busy): skip instead of bursting
            self._t0 = now - self._unit_index * unit_s
            self._next_due = now
        if out:
            self._write(bytes(out))

    def _angle_q6(self, sample_index: int, spr: int) -> int:
        """Device start angle (q6) of a sample index: evenly stepped, quantised like the device."""
        return int(round((sample_index % spr) * 360.0 * 64.0 / spr)) % (360 * 64)

    def _unit(self, mode: ScanMode, per_unit: int) -> bytes:
        spr = self._samples_per_rev(mode)
        i0 = self._sample_index
        self._sample_index += per_unit
        rev = i0 // spr
        if i0 % spr < per_unit:
            self.revolutions += 1
        if mode.answer_type == rp.ANS_STANDARD:
            a = self._angle_q6(i0, spr) / 64.0
            d = float(self.scene.ranges_mm(np.array([a]), rev)[0])
            data = rp.encode_standard_node(a, d, quality=47 if d > 0 else 0, start=(i0 % spr == 0))
        else:
            q0 = self._angle_q6(i0, spr)
            q1 = self._angle_q6(i0 + per_unit, spr)
            span = ((q1 - q0) % (360 * 64)) / 64.0
            angles = q0 / 64.0 + span * np.arange(per_unit) / per_unit
            first = self._unit_index == 0
            if mode.answer_type == rp.ANS_DENSE:
                d = self.scene.ranges_mm(np.mod(angles, 360.0), rev)
                data = rp.encode_dense_capsule(q0 / 64.0, d, new_scan=first)
            else:
                off = self._express_offsets(i0 % spr < per_unit, per_unit)
                # The sample taken at the raw angle a measured the direction a - offset (SDK).
                d = self.scene.ranges_mm(np.mod(angles - off / 8.0, 360.0), rev)
                data = rp.encode_express_capsule(q0 / 64.0, d, off, new_scan=first)
        self.units_sent += 1
        return self._apply_faults(data)

    def _express_offsets(self, after_wrap: bool, n: int) -> np.ndarray:
        """Random q3 angle offsets; at least 8 (1 deg) just after the wrap (see the class doc)."""
        hi = self.express_offset_max_q3
        if hi == 0:
            return np.zeros(n, np.int64)
        lo = min(8, hi) if after_wrap else 0
        return self.rng.integers(lo, hi + 1, n)

    def _apply_faults(self, data: bytes) -> bytes:
        k = self.units_sent
        with self._lock:
            f = self._faults
            garbage = b"".join(f.garbage)
            f.garbage.clear()
            corrupt = f.corrupt > 0 or (self.corrupt_every and k % self.corrupt_every == 0)
            truncate = f.truncate > 0 or (self.truncate_every and k % self.truncate_every == 0)
            f.corrupt = max(0, f.corrupt - 1)
            f.truncate = max(0, f.truncate - 1)
        if self.garbage_every and k % self.garbage_every == 0:
            garbage += self.rng.integers(0, 256, int(self.rng.integers(1, 40)), dtype=np.uint8).tobytes()
        if corrupt and len(data) > 4:
            b = bytearray(data)
            b[4 + int(self.rng.integers(0, len(data) - 4))] ^= 0x5A
            data = bytes(b)
        if truncate:
            data = data[:int(self.rng.integers(1, len(data)))]
        return garbage + data


# --- CLI ------------------------------------------------------------------------------------------

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--link", default="/tmp/racecav-rplidar", help="symlink to the pty (what `racecav sensor --port` opens)")
    p.add_argument("--replay", help=".npz of scans to replay (ranges, angle_min, angle_increment); default: fixed walls")
    p.add_argument("--reset-s", type=float, default=0.5, help="silence after RESET (a real S2 needs ~2 s)")
    p.add_argument("--garbage-every", type=int, default=0, help="inject random bytes every N scan units")
    p.add_argument("--corrupt-every", type=int, default=0, help="corrupt one byte of every Nth scan unit")
    p.add_argument("--truncate-every", type=int, default=0, help="truncate every Nth scan unit")
    p.add_argument("--unplug-every", type=float, default=0.0, help="simulate an unplug every S seconds")
    p.add_argument("--unplug-for", type=float, default=1.0, help="how long an unplug lasts (s)")
    p.add_argument("--express", action="store_true", help="also offer an Express mode (82, mode 2; not an S2 mode)")
    p.add_argument("--express-offset-max", type=int, default=63,
                   help="largest random express angle offset, q3 degrees 0..63 (0 = none)")


def run(args: argparse.Namespace, cfg=None) -> int:
    scene = ReplayScene(args.replay) if args.replay else None
    emu = RplidarEmulator(scene, link=args.link, reset_s=args.reset_s, garbage_every=args.garbage_every,
                          corrupt_every=args.corrupt_every, truncate_every=args.truncate_every,
                          modes=S2_MODES + ((EXPRESS_MODE,) if args.express else ()),
                          express_offset_max_q3=args.express_offset_max).start()
    print(emu.path, flush=True)
    print(emu.slave_name, file=sys.stderr, flush=True)
    stop = threading.Event()
    import signal

    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        next_unplug = time.monotonic() + args.unplug_every if args.unplug_every else math.inf
        while not stop.wait(0.1):
            if time.monotonic() >= next_unplug:
                emu.unplug(args.unplug_for)
                next_unplug = time.monotonic() + args.unplug_for + args.unplug_every
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    return 0
