"""RPLIDAR (S2 and kin) serial protocol: pure functions and a streaming parser, no I/O.

Byte layouts and test vectors: ../shared/reference/hardware-protocols.md (Slamtec SDK facts).
Everything here is used by both the driver (decoding) and the emulator (encoding), so the two
cannot disagree about a layout without the tests noticing.

Angles in this module are the device's own: degrees, clockwise seen from above, 0 at the
device's 0 mark. The conversion to REP-103 (counter-clockwise radians, car frame) happens in
:mod:`racecav.services.sensor.preprocess`.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

SYNC = 0xA5
SYNC2 = 0x5A

# Commands
CMD_STOP = 0x25
CMD_SCAN = 0x20
CMD_FORCE_SCAN = 0x21
CMD_RESET = 0x40
CMD_GET_INFO = 0x50
CMD_GET_HEALTH = 0x52
CMD_GET_SAMPLERATE = 0x59
CMD_EXPRESS_SCAN = 0x82
CMD_GET_LIDAR_CONF = 0x84
CMD_MOTOR_SPEED = 0xA8

# Answer types (last byte of a response descriptor)
ANS_INFO = 0x04
ANS_HEALTH = 0x06
ANS_CONF = 0x20
ANS_STANDARD = 0x81
ANS_EXPRESS = 0x82
ANS_ULTRA = 0x84
ANS_DENSE = 0x85

# GET_LIDAR_CONF types
CONF_SCAN_MODE_COUNT = 0x70
CONF_SCAN_MODE_US_PER_SAMPLE = 0x71
CONF_SCAN_MODE_MAX_DISTANCE = 0x74
CONF_SCAN_MODE_ANS_TYPE = 0x75
CONF_SCAN_MODE_TYPICAL = 0x7C
CONF_SCAN_MODE_NAME = 0x7F

MODE_SINGLE = 0
MODE_MULTI = 1  # streaming: units of `length` bytes repeat until STOP

HEALTH_OK, HEALTH_WARNING, HEALTH_ERROR = 0, 1, 2

STANDARD_NODE_LEN = 5
CAPSULE_LEN = 84
DENSE_SAMPLES = 40
EXPRESS_SAMPLES = 32
CAPSULE_SYNC_FLAG = 0x8000  # bit 15 of the start angle: first capsule after the scan started


class ProtocolError(ValueError):
    """Bytes that do not follow the protocol; the message says which field."""


# --- requests ---------------------------------------------------------------------------------

def request(cmd: int, payload: bytes = b"") -> bytes:
    """Encode a request: ``A5 cmd`` or ``A5 cmd size payload checksum`` (XOR of all before).

    :param cmd: command byte.
    :param payload: command payload; commands >= 0x80 carry one (possibly empty is not allowed
        by the device, but the encoding itself is defined for any size < 256).
    """
    if not payload and cmd < 0x80:
        return bytes((SYNC, cmd))
    if len(payload) > 255:
        raise ProtocolError(f"payload of {len(payload)} bytes does not fit the size byte")
    body = bytes((SYNC, cmd, len(payload))) + payload
    return body + bytes((xor8(body),))


def xor8(data: bytes | bytearray | memoryview) -> int:
    """XOR of all bytes (request checksums and capsule checksums)."""
    x = 0
    # int.from_bytes folds 8 bytes at a time: ~10x faster than a byte loop for 82-byte capsules.
    n = len(data) - len(data) % 8
    if n:
        acc = 0
        mv = memoryview(data)
        for i in range(0, n, 8):
            acc ^= int.from_bytes(mv[i:i + 8], "little")
        for _ in range(8):
            x ^= acc & 0xFF
            acc >>= 8
    for b in bytes(data[n:]):
        x ^= b
    return x


def motor_speed_request(rpm: int) -> bytes:
    """HQ_MOTOR_SPEED_CTRL (A8) with a u16 rpm; 0 stops the motor."""
    return request(CMD_MOTOR_SPEED, struct.pack("<H", rpm))


def express_scan_request(mode: int) -> bytes:
    """EXPRESS_SCAN (82) for a scan mode id: payload ``<B mode><H flags=0><H param=0>``."""
    return request(CMD_EXPRESS_SCAN, struct.pack("<BHH", mode, 0, 0))


def conf_request(conf_type: int, mode: int | None = None) -> bytes:
    """GET_LIDAR_CONF (84): payload ``<I type>`` plus ``<H mode>`` for per-mode queries."""
    payload = struct.pack("<I", conf_type)
    if mode is not None:
        payload += struct.pack("<H", mode)
    return request(CMD_GET_LIDAR_CONF, payload)


@dataclass(frozen=True)
class Request:
    """A request parsed from the device side (emulator)."""

    cmd: int
    payload: bytes = b""


class RequestParser:
    """Device-side parser of the request grammar; drops bytes that are not a valid request.

    Commands >= 0x80 carry ``size payload checksum``; a bad checksum drops the request (the real
    device ignores it too) and is counted in ``errors``.
    """

    def __init__(self) -> None:
        self.buf = bytearray()
        self.errors = 0

    def feed(self, data: bytes) -> list[Request]:
        self.buf += data
        out: list[Request] = []
        while True:
            i = self.buf.find(SYNC)
            if i < 0:
                self.errors += bool(self.buf)
                self.buf.clear()
                return out
            if i:
                self.errors += 1
                del self.buf[:i]
            if len(self.buf) < 2:
                return out
            cmd = self.buf[1]
            if cmd < 0x80:
                out.append(Request(cmd))
                del self.buf[:2]
                continue
            if len(self.buf) < 3 or len(self.buf) < 4 + self.buf[2]:
                return out
            size = self.buf[2]
            frame = bytes(self.buf[:4 + size])
            if xor8(frame[:-1]) != frame[-1]:
                self.errors += 1
                del self.buf[:1]
                continue
            out.append(Request(cmd, frame[3:3 + size]))
            del self.buf[:4 + size]


# --- response descriptors ---------------------------------------------------------------------

@dataclass(frozen=True)
class Descriptor:
    """``A5 5A`` + u32 LE (low 30 bits length, top 2 bits send mode) + answer type."""

    length: int
    mode: int
    dtype: int

    def encode(self) -> bytes:
        return bytes((SYNC, SYNC2)) + struct.pack("<I", (self.length & 0x3FFFFFFF) | (self.mode << 30)) \
            + bytes((self.dtype,))

    @classmethod
    def parse(cls, data: bytes) -> "Descriptor":
        if len(data) != 7:
            raise ProtocolError(f"descriptor: expected 7 bytes, got {len(data)}")
        if data[0] != SYNC or data[1] != SYNC2:
            raise ProtocolError(f"descriptor: bad sync {data[:2].hex()}")
        (word,) = struct.unpack_from("<I", data, 2)
        return cls(word & 0x3FFFFFFF, word >> 30, data[6])


@dataclass(frozen=True)
class DeviceInfo:
    model: int
    firmware: tuple[int, int]
    hardware: int
    serial: str

    @property
    def model_major(self) -> int:
        """7 for the S2."""
        return self.model >> 4

    def encode(self) -> bytes:
        return struct.pack("<BBBB", self.model, self.firmware[1], self.firmware[0], self.hardware) \
            + bytes.fromhex(self.serial)

    @classmethod
    def parse(cls, data: bytes) -> "DeviceInfo":
        if len(data) < 20:
            raise ProtocolError(f"info: expected 20 bytes, got {len(data)}")
        model, fw_minor, fw_major, hw = struct.unpack_from("<BBBB", data)
        return cls(model, (fw_major, fw_minor), hw, data[4:20].hex().upper())


@dataclass(frozen=True)
class Health:
    status: int
    error_code: int

    def encode(self) -> bytes:
        return struct.pack("<BH", self.status, self.error_code)

    @classmethod
    def parse(cls, data: bytes) -> "Health":
        if len(data) < 3:
            raise ProtocolError(f"health: expected 3 bytes, got {len(data)}")
        return cls(*struct.unpack_from("<BH", data))


def parse_conf_answer(conf_type: int, data: bytes) -> bytes:
    """Check the echoed u32 conf type of a GET_LIDAR_CONF answer and return the data after it."""
    if len(data) < 4:
        raise ProtocolError(f"lidar conf: answer of {len(data)} bytes has no type echo")
    (echo,) = struct.unpack_from("<I", data)
    if echo != conf_type:
        raise ProtocolError(f"lidar conf: asked type {conf_type:#x}, answer echoes {echo:#x}")
    return data[4:]


# --- standard scan nodes (81) -----------------------------------------------------------------

def encode_standard_node(angle_deg: float, dist_mm: float, quality: int = 47, start: bool = False) -> bytes:
    """One 5-byte node: b0 = quality<<2 | !S<<1 | S; angle_q6<<1 | 1; distance_q2."""
    s = 1 if start else 0
    b0 = ((quality & 0x3F) << 2) | ((1 - s) << 1) | s
    angle_q6 = int(round(angle_deg * 64.0)) % (360 * 64)
    return struct.pack("<BHH", b0, (angle_q6 << 1) | 1, min(int(round(dist_mm * 4.0)), 0xFFFF))


def standard_node_valid(node: bytes) -> bool:
    """Check bits: (bit0 xor bit1) of b0 == 1 and bit0 of b1 == 1."""
    return ((node[0] ^ (node[0] >> 1)) & 1) == 1 and (node[1] & 1) == 1


def decode_standard_nodes(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Decode an (n, 5) uint8 array of nodes already known to be valid.

    :returns: angle_deg, dist_mm, quality, start flag arrays.
    """
    b = buf.astype(np.uint32)
    start = (b[:, 0] & 1).astype(bool)
    quality = (b[:, 0] >> 2).astype(np.uint8)
    angle = ((b[:, 1] | (b[:, 2] << 8)) >> 1).astype(np.float64) / 64.0
    dist = (b[:, 3] | (b[:, 4] << 8)).astype(np.float64) / 4.0
    return angle, dist, quality, start


# --- capsules (82 express, 85 dense) ----------------------------------------------------------

def capsule_header_ok(data: bytes | bytearray, i: int = 0) -> bool:
    """Sync nibbles: high nibble of byte 0 is A, of byte 1 is 5."""
    return (data[i] >> 4) == 0xA and (data[i + 1] >> 4) == 0x5


def capsule_checksum_ok(cap: bytes | bytearray | memoryview) -> bool:
    """Checksum (low nibbles of bytes 0 and 1) == XOR of bytes 2..83."""
    want = (cap[0] & 0x0F) | ((cap[1] & 0x0F) << 4)
    return xor8(cap[2:CAPSULE_LEN]) == want


def capsule_start(cap: bytes | bytearray | memoryview) -> tuple[float, bool]:
    """Start angle in degrees and the "new scan" flag of a capsule."""
    w = cap[2] | (cap[3] << 8)
    return (w & 0x7FFF) / 64.0, bool(w & CAPSULE_SYNC_FLAG)


def _seal_capsule(body: bytes) -> bytes:
    """Prefix the 82 checksummed bytes with the two sync/checksum bytes."""
    c = xor8(body)
    return bytes((0xA0 | (c & 0x0F), 0x50 | (c >> 4))) + body


def encode_dense_capsule(start_deg: float, distances_mm, new_scan: bool = False) -> bytes:
    """An 84-byte dense capsule (85): header + 40 u16 LE distances in whole mm."""
    d = np.clip(np.rint(np.asarray(distances_mm, dtype=np.float64)), 0, 0xFFFF).astype("<u2")
    if d.shape != (DENSE_SAMPLES,):
        raise ProtocolError(f"dense capsule: need {DENSE_SAMPLES} distances, got {d.shape}")
    w = (int(round(start_deg * 64.0)) % (360 * 64)) | (CAPSULE_SYNC_FLAG if new_scan else 0)
    return _seal_capsule(struct.pack("<H", w) + d.tobytes())


def dense_distances(cap: bytes | bytearray | memoryview) -> np.ndarray:
    """The 40 distances (mm) of a dense capsule."""
    return np.frombuffer(bytes(cap[4:CAPSULE_LEN]), dtype="<u2").astype(np.float64)


def encode_express_capsule(start_deg: float, distances_mm, offsets_q3=None, new_scan: bool = False) -> bytes:
    """An 84-byte express capsule (82): 16 cabins of (u16 d1, u16 d2, u8 offset nibbles).

    Distances are stored q2 in the top 14 bits; the two low bits carry bits 4-5 of the angle
    offset. Offsets default to 0 (samples exactly on the interpolated angles).
    """
    d = np.clip(np.rint(np.asarray(distances_mm, dtype=np.float64) * 4.0), 0, 0xFFFF).astype(np.int64) & 0xFFFC
    off = np.zeros(EXPRESS_SAMPLES, np.int64) if offsets_q3 is None else np.asarray(offsets_q3, np.int64) & 0x3F
    if d.shape != (EXPRESS_SAMPLES,):
        raise ProtocolError(f"express capsule: need {EXPRESS_SAMPLES} distances, got {d.shape}")
    body = bytearray(struct.pack("<H", (int(round(start_deg * 64.0)) % (360 * 64)) | (CAPSULE_SYNC_FLAG if new_scan else 0)))
    for c in range(16):
        d1 = int(d[2 * c]) | (int(off[2 * c]) >> 4)
        d2 = int(d[2 * c + 1]) | (int(off[2 * c + 1]) >> 4)
        body += struct.pack("<HHB", d1, d2, (int(off[2 * c]) & 0xF) | ((int(off[2 * c + 1]) & 0xF) << 4))
    return _seal_capsule(bytes(body))


def express_samples(cap: bytes | bytearray | memoryview) -> tuple[np.ndarray, np.ndarray]:
    """Distances (mm) and angle offsets (deg) of the 32 samples of an express capsule.

    The device reports sample angles as interpolated minus the offset (Slamtec SDK).
    """
    raw = np.frombuffer(bytes(cap[4:CAPSULE_LEN]), dtype=np.uint8).reshape(16, 5).astype(np.int64)
    d1 = raw[:, 0] | (raw[:, 1] << 8)
    d2 = raw[:, 2] | (raw[:, 3] << 8)
    o1 = (raw[:, 4] & 0xF) | ((d1 & 3) << 4)
    o2 = (raw[:, 4] >> 4) | ((d2 & 3) << 4)
    dist = np.stack([d1 & 0xFFFC, d2 & 0xFFFC], axis=1).reshape(-1).astype(np.float64) / 4.0
    off = np.stack([o1, o2], axis=1).reshape(-1).astype(np.float64) / 8.0
    return dist, off


# --- streaming parser -------------------------------------------------------------------------

@dataclass
class Samples:
    """A batch of decoded measurements, in arrival order.

    ``angle_deg`` is where each sample was measured. ``raw_deg`` is the sweep angle it was taken
    at: the capsule's interpolated angle before the express angle offset is subtracted (equal to
    ``angle_deg`` for standard and dense data). The raw angle rises monotonically through a turn,
    the corrected one does not (an offset of up to 7.9 deg can put a sample taken just after
    0 deg before it), so turns are found from the raw angle, as the Slamtec SDK does.

    ``start`` marks the first sample of a new revolution (the raw angle wrapped past 0 deg, or
    the device's S flag in standard mode).
    """

    angle_deg: np.ndarray
    dist_mm: np.ndarray
    start: np.ndarray
    raw_deg: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.raw_deg is None:
            self.raw_deg = self.angle_deg

    @classmethod
    def empty(cls) -> "Samples":
        return cls(np.zeros(0), np.zeros(0), np.zeros(0, bool))


@dataclass
class ParserStats:
    """What the parser dropped, by reason."""

    checksum: int = 0
    """Capsules whose checksum did not match (corrupt, or a truncated capsule's bytes)."""
    resync_bytes: int = 0
    """Bytes skipped while looking for the next valid node/capsule header."""
    bad_nodes: int = 0
    """Standard nodes whose check bits were wrong."""
    angle_jumps: int = 0
    """Capsule pairs discarded because their angle difference was implausible."""
    capsules: int = 0
    nodes: int = 0
    samples: int = 0

    def errors(self) -> int:
        return self.checksum + self.bad_nodes + self.angle_jumps

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class ScanStream:
    """Streaming decoder of a scan's data (after its descriptor) for answer type 81, 82 or 85.

    Feed it whatever bytes the port returned; it returns the samples it could decode and keeps
    the rest. Garbage, lost bytes and truncated capsules are skipped by resynchronising on the
    next header whose check bits/checksum are right; every drop is counted in ``stats``.

    A capsule is decoded only once the next one has arrived: its samples lie evenly between the
    two start angles (difference taken modulo 360). A pair whose difference exceeds
    ``max_capsule_span_deg`` (e.g. capsules lost in between) is discarded, like the SDK does.

    :param answer_type: ANS_STANDARD, ANS_EXPRESS or ANS_DENSE.
    :param max_capsule_span_deg: largest plausible angle between consecutive capsules.
    """

    answer_type: int
    max_capsule_span_deg: float = 20.0
    stats: ParserStats = field(default_factory=ParserStats)

    def __post_init__(self) -> None:
        if self.answer_type not in (ANS_STANDARD, ANS_EXPRESS, ANS_DENSE):
            raise ProtocolError(f"scan answer type {self.answer_type:#x} not supported")
        self.buf = bytearray()
        self._prev: bytes | None = None  # last capsule, waiting for its successor
        self._last_raw: float | None = None  # raw angle of the last emitted sample (wrap detection)
        self._gap = False  # bytes were skipped since the last good capsule
        self._span = 0.0  # running estimate of the angle between consecutive capsules
        n = DENSE_SAMPLES if self.answer_type == ANS_DENSE else EXPRESS_SAMPLES
        self._frac = np.arange(n) / n  # sample positions within a capsule's span

    def reset(self) -> None:
        """Forget partial data (after a restart of the scan)."""
        self.buf.clear()
        self._prev = None
        self._last_raw = None
        self._gap = False
        self._span = 0.0

    def feed(self, data: bytes) -> Samples:
        self.buf += data
        if self.answer_type == ANS_STANDARD:
            return self._feed_standard()
        return self._feed_capsules()

    # standard ---------------------------------------------------------------------------------

    def _feed_standard(self) -> Samples:
        parts: list[np.ndarray] = []
        while len(self.buf) >= STANDARD_NODE_LEN:
            n = len(self.buf) // STANDARD_NODE_LEN
            arr = np.frombuffer(bytes(self.buf[:n * STANDARD_NODE_LEN]), np.uint8).reshape(n, STANDARD_NODE_LEN)
            ok = (((arr[:, 0] ^ (arr[:, 0] >> 1)) & 1) == 1) & ((arr[:, 1] & 1) == 1)
            bad = np.flatnonzero(~ok)
            good = n if bad.size == 0 else int(bad[0])
            if good:
                parts.append(arr[:good])
                del self.buf[:good * STANDARD_NODE_LEN]
            if bad.size:
                # Misaligned or corrupted: drop one byte and look again.
                self.stats.bad_nodes += 1
                self.stats.resync_bytes += 1
                del self.buf[:1]
        if not parts:
            return Samples.empty()
        nodes = np.concatenate(parts)
        self.stats.nodes += len(nodes)
        angle, dist, _q, start = decode_standard_nodes(nodes)
        self.stats.samples += len(angle)
        return Samples(angle, dist, start)

    # capsules ---------------------------------------------------------------------------------

    def _feed_capsules(self) -> Samples:
        angles: list[np.ndarray] = []
        dists: list[np.ndarray] = []
        raws: list[np.ndarray] = []
        buf = self.buf
        i = 0
        end = len(buf)
        while end - i >= CAPSULE_LEN:
            if not capsule_header_ok(buf, i):
                i += 1
                self.stats.resync_bytes += 1
                self._gap = True
                continue
            cap = bytes(buf[i:i + CAPSULE_LEN])
            if not capsule_checksum_ok(cap):
                self.stats.checksum += 1
                self.stats.resync_bytes += 1
                self._gap = True
                i += 1
                continue
            i += CAPSULE_LEN
            self.stats.capsules += 1
            out = self._pair(cap)
            if out is not None:
                angles.append(out[0])
                dists.append(out[1])
                raws.append(out[2])
        del buf[:i]
        if not angles:
            return Samples.empty()
        a = np.concatenate(angles)
        d = np.concatenate(dists)
        raw = np.concatenate(raws)
        self.stats.samples += len(a)
        return Samples(a, d, self._wraps(raw), raw)

    def _pair(self, cap: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Decode the previous capsule now that ``cap`` follows it: (angle, dist, raw angle)."""
        start, new_scan = capsule_start(cap)
        prev, self._prev = self._prev, cap
        gap, self._gap = self._gap, False
        if gap and prev is not None:
            # Something was lost between the two: the span would spread prev's samples over
            # the missing capsule's angles too. Drop prev (as the SDK drops the pair).
            self.stats.angle_jumps += 1
            return None
        if new_scan:
            # First capsule of a (re)started scan: whatever came before belongs to another scan.
            self._last_raw = None
            return None
        if prev is None:
            return None
        prev_start, _ = capsule_start(prev)
        span = (start - prev_start) % 360.0
        if span == 0.0 or span > self.max_capsule_span_deg or (self._span and span > 1.5 * self._span):
            # Implausible: a whole capsule lost without a byte of garbage, or a bad start angle.
            self.stats.angle_jumps += 1
            return None
        self._span = span if not self._span else 0.9 * self._span + 0.1 * span
        raw = prev_start + span * self._frac  # evenly spread between the two start angles
        if self.answer_type == ANS_DENSE:
            raw = np.mod(raw, 360.0)
            return raw, dense_distances(prev), raw
        dist, off = express_samples(prev)
        angle = np.mod(raw - off, 360.0)  # the SDK: angle = raw - offset (q3 degrees)
        return angle, dist, np.mod(raw, 360.0)

    def _wraps(self, raw: np.ndarray) -> np.ndarray:
        """Mark samples whose raw angle went backwards by more than half a turn: a new revolution.

        The raw angle (before the express offset) rises evenly through a turn, so this fires
        exactly once per turn. The SDK's test, ``(raw_i + inc) % 360 < inc``, flags the sample
        just before the wrap; racecav flags the first sample after it (one sample later), which
        is the first sample of the new turn.
        """
        prev = np.empty_like(raw)
        prev[0] = raw[0] if self._last_raw is None else self._last_raw
        prev[1:] = raw[:-1]
        self._last_raw = float(raw[-1])
        return (prev - raw) > 180.0


@dataclass
class Revolution:
    """One full turn of samples, in arrival order (device angles)."""

    angle_deg: np.ndarray
    dist_mm: np.ndarray
    t_end: float = 0.0
    """Monotonic time (s) at which the last bytes of the revolution were read."""


def _half_turn_away(rel: np.ndarray) -> bool:
    """Whether any angle (relative to the cut) lies between 90 and 270 deg: re-arms the cut."""
    return bool(np.any(np.abs(rel - 180.0) <= 90.0))


class RevolutionAssembler:
    """Cut a stream of samples into revolutions where the sweep passes ``cut_deg``.

    The cut is a device angle chosen by the user of the revolutions: cutting just after the
    sector of interest makes that sector contiguous and publishes it as soon as it is complete
    (the device's own 0 deg would split a frontal sector between two turns). The partial turn
    before the first cut is discarded.

    The cut is decided on the raw sweep angle (:attr:`Samples.raw_deg`, before the express
    offset), which rises monotonically, so a turn is cut exactly once and no sample is lost (the
    corrected angles of express samples go back and forth by up to 7.9 deg around the cut). As a
    second guard (standard-mode nodes carry measured angles that can jitter), a cut re-arms only
    once the sweep has been seen between 90 and 270 deg past the cut.

    :param cut_deg: device angle (deg) where a revolution starts.
    :param min_samples: revolutions with fewer samples (e.g. cut short by an error) are dropped
        and counted in ``short``.
    """

    def __init__(self, cut_deg: float = 0.0, min_samples: int = 100):
        self.cut = cut_deg % 360.0
        self.min_samples = min_samples
        self._a: list[np.ndarray] = []
        self._d: list[np.ndarray] = []
        self._last: float | None = None
        self._started = False
        self._armed = True
        self.short = 0

    def reset(self) -> None:
        self._a, self._d = [], []
        self._last = None
        self._started = False
        self._armed = True

    def add(self, s: Samples, t: float = 0.0) -> list[Revolution]:
        if len(s.angle_deg) == 0:
            return []
        rel = np.mod(s.raw_deg - self.cut, 360.0)
        prev = np.empty_like(rel)
        prev[0] = rel[0] if self._last is None else self._last
        prev[1:] = rel[:-1]
        self._last = float(rel[-1])
        out: list[Revolution] = []
        lo = 0
        for c in np.flatnonzero(prev - rel > 180.0):
            if not (self._armed or _half_turn_away(rel[lo:c])):
                continue  # the sweep stepped back across the cut: still the same turn
            self._armed = False
            if self._started:
                self._a.append(s.angle_deg[lo:c])
                self._d.append(s.dist_mm[lo:c])
                rev = Revolution(np.concatenate(self._a), np.concatenate(self._d), t)
                if len(rev.angle_deg) >= self.min_samples:
                    out.append(rev)
                else:
                    self.short += 1
            self._a, self._d = [], []
            self._started = True
            lo = c
        self._armed = self._armed or _half_turn_away(rel[lo:])
        if self._started:
            self._a.append(s.angle_deg[lo:])
            self._d.append(s.dist_mm[lo:])
        return out
