"""VESC serial protocol: framing, CRC-16/XMODEM, commands, GET_VALUES. Pure functions, no I/O.

Frame: ``02 len payload crc_hi crc_lo 03`` (payload < 256 bytes) or ``03 len_hi len_lo payload
crc_hi crc_lo 03``; the CRC covers the payload only; integers are big-endian. Layouts and test
vectors: ../shared/reference/hardware-protocols.md. Used by the actuator (encode commands, parse
replies) and by the emulator (parse commands, encode replies).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

COMM_FW_VERSION = 0x00
COMM_GET_VALUES = 0x04
COMM_SET_DUTY = 0x05
COMM_SET_CURRENT = 0x06
COMM_SET_CURRENT_BRAKE = 0x07
COMM_SET_RPM = 0x08
COMM_SET_POS = 0x09
COMM_SET_SERVO_POS = 0x0C
COMM_ALIVE = 0x1E

NAMES = {COMM_FW_VERSION: "FW_VERSION", COMM_GET_VALUES: "GET_VALUES", COMM_SET_DUTY: "SET_DUTY",
         COMM_SET_CURRENT: "SET_CURRENT", COMM_SET_CURRENT_BRAKE: "SET_CURRENT_BRAKE",
         COMM_SET_RPM: "SET_RPM", COMM_SET_POS: "SET_POS", COMM_SET_SERVO_POS: "SET_SERVO_POS",
         COMM_ALIVE: "ALIVE"}

MAX_PAYLOAD = 1024  # longer frames (configuration dumps) are not something this car sends or expects


class FrameError(ValueError):
    """A frame or payload that does not follow the protocol; the message names the field."""


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16/XMODEM: poly 0x1021, init 0, no reflection, no final XOR (check "123456789" = 0x31C3)."""
    c = 0
    for b in data:
        c = ((c << 8) & 0xFFFF) ^ _CRC_TABLE[((c >> 8) ^ b) & 0xFF]
    return c


def frame(payload: bytes) -> bytes:
    """Wrap a payload in a short (02) or long (03) frame."""
    n = len(payload)
    if n == 0 or n > 0xFFFF:
        raise FrameError(f"payload length {n} not framable")
    head = bytes((0x02, n)) if n < 256 else bytes((0x03, n >> 8, n & 0xFF))
    return head + payload + struct.pack(">H", crc16(payload)) + b"\x03"


# --- commands ------------------------------------------------------------------------------------

def _i32(cmd: int, value: float, scale: float) -> bytes:
    v = int(round(value * scale))
    if not -2**31 <= v < 2**31:
        raise FrameError(f"{NAMES[cmd]}: value {value} out of i32 range")
    return frame(struct.pack(">Bi", cmd, v))


def set_rpm(erpm: float) -> bytes:
    """SET_RPM: electrical RPM, i32."""
    return _i32(COMM_SET_RPM, erpm, 1.0)


def set_duty(duty: float) -> bytes:
    """SET_DUTY: duty cycle in [-1, 1], i32 x 1e5."""
    return _i32(COMM_SET_DUTY, duty, 1e5)


def set_current(amps: float) -> bytes:
    """SET_CURRENT: motor current (A), i32 x 1000."""
    return _i32(COMM_SET_CURRENT, amps, 1000.0)


def set_current_brake(amps: float) -> bytes:
    """SET_CURRENT_BRAKE: braking current (A), i32 x 1000."""
    return _i32(COMM_SET_CURRENT_BRAKE, amps, 1000.0)


def set_servo_pos(pos: float) -> bytes:
    """SET_SERVO_POS: servo position in [0, 1], i16 x 1000."""
    if not 0.0 <= pos <= 1.0:
        raise FrameError(f"SET_SERVO_POS: position {pos} outside [0, 1]")
    return frame(struct.pack(">Bh", COMM_SET_SERVO_POS, int(round(pos * 1000))))


def get_values() -> bytes:
    return frame(bytes((COMM_GET_VALUES,)))


def alive() -> bytes:
    return frame(bytes((COMM_ALIVE,)))


def fw_version() -> bytes:
    return frame(bytes((COMM_FW_VERSION,)))


@dataclass(frozen=True)
class Command:
    """A decoded command payload (emulator side): name and value in physical units."""

    cmd: int
    value: float | None = None

    @property
    def name(self) -> str:
        return NAMES.get(self.cmd, f"CMD_{self.cmd:02X}")


_SCALES = {COMM_SET_DUTY: 1e5, COMM_SET_CURRENT: 1000.0, COMM_SET_CURRENT_BRAKE: 1000.0,
           COMM_SET_RPM: 1.0, COMM_SET_POS: 1e6}


def parse_command(payload: bytes) -> Command:
    """Decode a command payload; unknown ids come back with value None."""
    if not payload:
        raise FrameError("empty payload")
    cmd = payload[0]
    if cmd in _SCALES:
        if len(payload) < 5:
            raise FrameError(f"{NAMES[cmd]}: payload of {len(payload)} bytes, need 5")
        return Command(cmd, struct.unpack_from(">i", payload, 1)[0] / _SCALES[cmd])
    if cmd == COMM_SET_SERVO_POS:
        if len(payload) < 3:
            raise FrameError(f"SET_SERVO_POS: payload of {len(payload)} bytes, need 3")
        return Command(cmd, struct.unpack_from(">h", payload, 1)[0] / 1000.0)
    return Command(cmd)


# --- GET_VALUES -----------------------------------------------------------------------------------

# The reply's fields in the firmware's order (vedderb/bldc comm/commands.c, COMM_GET_VALUES with
# every mask bit set): (name, struct format, scale). The firmware writes int(value * scale)
# big-endian; offsets follow from the order, payload[0] being the command id 04. Current firmware
# sends all of them: 74 bytes. Older firmware stops earlier (after `fault`: 54 bytes).
VALUES_FIELDS = (
    ("temp_fet", ">h", 1e1), ("temp_motor", ">h", 1e1),
    ("avg_motor_current", ">i", 1e2), ("avg_input_current", ">i", 1e2),
    ("avg_id", ">i", 1e2), ("avg_iq", ">i", 1e2),
    ("duty", ">h", 1e3), ("rpm", ">i", 1.0), ("v_in", ">h", 1e1),
    ("amp_hours", ">i", 1e4), ("amp_hours_charged", ">i", 1e4),
    ("watt_hours", ">i", 1e4), ("watt_hours_charged", ">i", 1e4),
    ("tachometer", ">i", 1.0), ("tachometer_abs", ">i", 1.0), ("fault", ">B", 1.0),
    ("pid_pos", ">i", 1e6), ("controller_id", ">B", 1.0),
    ("temp_mos1", ">h", 1e1), ("temp_mos2", ">h", 1e1), ("temp_mos3", ">h", 1e1),
    ("avg_vd", ">i", 1e3), ("avg_vq", ">i", 1e3),
    ("status", ">B", 1.0),  # bit 0: the app timeout has expired; bit 1: kill switch active
)


def _layout() -> tuple[tuple[str, int, str, float], ...]:
    out, off = [], 1
    for name, fmt, scale in VALUES_FIELDS:
        out.append((name, off, fmt, scale))
        off += struct.calcsize(fmt)
    return tuple(out)


VALUES_LAYOUT = _layout()
"""(name, offset into the payload, struct format, scale), derived from VALUES_FIELDS."""
VALUES_LEN = VALUES_LAYOUT[-1][1] + struct.calcsize(VALUES_LAYOUT[-1][2])
"""74: the reply payload of current firmware, command id included."""
STATUS_TIMEOUT, STATUS_KILL_SWITCH = 0x01, 0x02


def parse_values(payload: bytes) -> dict[str, float]:
    """GET_VALUES reply -> dict, reading the fields in the firmware's order.

    Fields beyond the payload's length are absent (older firmware sends fewer: parse what is
    there, never guess); bytes after the last field racecav knows (a newer firmware's additions)
    are ignored. Integer fields stay ints; the others are divided by their scale.

    :raises FrameError: if the payload is not a GET_VALUES reply.
    """
    if not payload or payload[0] != COMM_GET_VALUES:
        raise FrameError(f"GET_VALUES reply: first byte {payload[:1].hex() or 'missing'}, expected 04")
    out: dict[str, float] = {}
    for name, off, fmt, scale in VALUES_LAYOUT:
        size = struct.calcsize(fmt)
        if off + size > len(payload):
            break
        v = struct.unpack_from(fmt, payload, off)[0]
        out[name] = int(v) if scale == 1.0 else v / scale
    return out


def encode_values(values: dict[str, float], length: int = VALUES_LEN) -> bytes:
    """Build a GET_VALUES reply payload (emulator) with the fields that fit in ``length`` bytes.

    :param values: field values in physical units; missing fields are 0.
    :param length: payload length to emit, cut at a field boundary (54 = older firmware).
    """
    out = bytearray(bytes((COMM_GET_VALUES,)))
    for name, off, fmt, scale in VALUES_LAYOUT:
        if off + struct.calcsize(fmt) > length:
            break
        out += struct.pack(fmt, int(round(values.get(name, 0) * scale)))
    return bytes(out)


# --- streaming parser -----------------------------------------------------------------------------

class FrameParser:
    """Split a byte stream into payloads; skips garbage and bad frames (counted in ``errors``).

    A corrupted byte can look like the header of a long frame and make the parser wait for
    bytes that will never form it; so while a frame is incomplete, a complete valid frame found
    further on wins and the false start is dropped.
    """

    def __init__(self) -> None:
        self.buf = bytearray()
        self.errors = 0

    @staticmethod
    def _check(buf: bytearray, i: int) -> tuple[str, int]:
        """("ok" | "bad" | "short", total length) of a frame candidate starting at buf[i]."""
        start = buf[i]
        if start not in (0x02, 0x03):
            return "bad", 0
        head = 2 if start == 0x02 else 3
        if len(buf) - i < head:
            return "short", 0
        n = buf[i + 1] if start == 0x02 else (buf[i + 1] << 8) | buf[i + 2]
        if n == 0 or n > MAX_PAYLOAD:
            return "bad", 0
        total = head + n + 3
        if len(buf) - i < total:
            return "short", total
        end = i + head + n
        if buf[i + total - 1] != 0x03 or crc16(bytes(buf[i + head:end])) != (buf[end] << 8) | buf[end + 1]:
            return "bad", total
        return "ok", total

    def feed(self, data: bytes) -> list[bytes]:
        self.buf += data
        out: list[bytes] = []
        buf = self.buf
        while buf:
            state, total = self._check(buf, 0)
            if state == "ok":
                head = 2 if buf[0] == 0x02 else 3
                out.append(bytes(buf[head:total - 3]))
                del buf[:total]
            elif state == "bad":
                del buf[:1]  # resync: the real frame may start inside this one
                self.errors += 1
            else:
                later = next((j for j in range(1, len(buf)) if self._check(buf, j)[0] == "ok"), None)
                if later is None:
                    break  # genuinely incomplete: wait for more bytes
                del buf[:later]
                self.errors += 1
        return out
