"""Wire format: one msgpack map per message.

``{"v": SCHEMA_VERSION, "t": <type>, <field>: <value>, ...}`` with field names as in
:mod:`racecav.common.messages`; float32 arrays travel as raw little-endian bytes (msgpack bin),
so any msgpack client can read a message (numpy: ``np.frombuffer(m["ranges"], "<f4")``).

:func:`decode` validates everything and raises :class:`DecodeError` (with a ``kind``) on any
malformed input, and nothing else: it never returns a half-valid message and never lets another
exception type out (a subscriber callback can rely on catching DecodeError only). Validation is
strict: no coercion of strings or booleans into numbers (``"1.0"`` or ``true`` in a float field is
an error), integers must fit int64, floats must be finite and within each field's range
(:mod:`racecav.common.messages`).
"""

from __future__ import annotations

from typing import TypeVar

import msgpack
import numpy as np
from pydantic import BaseModel, ValidationError

from racecav.common.messages import MESSAGE_TYPES, Message

SCHEMA_VERSION = 1
MAX_PAYLOAD_BYTES = 65536

M = TypeVar("M", bound=Message)


class DecodeError(ValueError):
    """A payload that is not a valid message. ``kind`` is one of: oversize, msgpack, version,
    type, schema."""

    def __init__(self, kind: str, detail: str):
        super().__init__(f"{kind}: {detail}")
        self.kind = kind


def _wire(v):
    if isinstance(v, np.ndarray):
        return v.astype("<f4", copy=False).tobytes()
    if isinstance(v, list) and v and isinstance(v[0], BaseModel):
        return [x.model_dump() for x in v]
    return v


def encode(msg: Message) -> bytes:
    """Serialise a message (arrays as little-endian float32 bytes).

    :raises ValueError: a field that msgpack cannot carry (e.g. an integer beyond 64 bits set
        without validation); never a half-written payload.
    """
    d = {"v": SCHEMA_VERSION, "t": msg.TYPE}
    for k, v in msg.__dict__.items():  # faster than model_dump() on the 60 Hz scan path
        d[k] = _wire(v)
    try:
        return msgpack.packb(d, use_bin_type=True)
    except (OverflowError, TypeError, ValueError) as e:
        raise ValueError(f"encode {msg.TYPE}: {type(e).__name__}: {e}") from None


def decode(data: bytes | bytearray | memoryview, cls: type[M] | None = None,
           max_bytes: int = MAX_PAYLOAD_BYTES) -> M:
    """Parse and validate a payload.

    :param cls: the expected message class; None accepts any known type.
    :raises DecodeError: on oversize, non-msgpack, wrong version, wrong type or invalid fields.
    """
    try:
        return _decode(data, cls, max_bytes)
    except DecodeError:
        raise
    except Exception as e:  # a validator bug or an exotic input: still only a DecodeError
        raise DecodeError("schema", f"{type(e).__name__}: {e}") from None


def _decode(data, cls, max_bytes):
    if len(data) > max_bytes:
        raise DecodeError("oversize", f"{len(data)} bytes > {max_bytes}")
    try:
        d = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=max_bytes,
                            max_str_len=max_bytes, max_array_len=4096, max_map_len=256)
    except Exception as e:  # msgpack raises several unrelated exception types
        raise DecodeError("msgpack", f"{type(e).__name__}: {e}") from None
    if not isinstance(d, dict):
        raise DecodeError("msgpack", f"expected a map, got {type(d).__name__}")
    version = d.pop("v", None)
    if version != SCHEMA_VERSION:
        raise DecodeError("version", f"schema version {version!r}, expected {SCHEMA_VERSION}")
    t = d.pop("t", None)
    target = MESSAGE_TYPES.get(t) if isinstance(t, str) else None
    if target is None or (cls is not None and target is not cls):
        want = cls.TYPE if cls is not None else "a known type"
        raise DecodeError("type", f"message type {t!r}, expected {want}")
    try:
        return target.model_validate(d, strict=True)  # type: ignore[return-value]
    except ValidationError as e:
        err = e.errors(include_url=False)[0]
        field = ".".join(str(p) for p in err["loc"]) or "message"
        raise DecodeError("schema", f"{target.TYPE}.{field}: {err['msg']}") from None
