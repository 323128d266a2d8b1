"""Client-side helpers for tools and tests: who is alive, what is their status.

These use only public Zenoh calls, so the same can be done from any Zenoh client (see README).
"""

from __future__ import annotations

import json
from typing import Any

import zenoh

from racecav.common import keys
from racecav.common.bus import zenoh_config
from racecav.common.codec import decode
from racecav.common.config import Config
from racecav.common.messages import Message, ServiceStatus


def open_session(cfg: Config) -> zenoh.Session:
    """A client session per the bus config (close it, or use ``with``)."""
    return zenoh.open(zenoh_config(cfg.bus))


def live_services(session: zenoh.Session, car: str, timeout: float = 1.0) -> list[str]:
    """Names of services holding a liveliness token on this car."""
    names = set()
    for reply in session.liveliness().get(keys.alive_key(car), timeout=timeout):
        if reply.ok is not None:
            names.add(str(reply.ok.key_expr).split("/")[2])
    return sorted(names)


def query(session: zenoh.Session, key: str, payload: bytes | None = None, timeout: float = 2.0) -> bytes:
    """One reply's payload from a queryable; raises RuntimeError on error or no reply."""
    for reply in session.get(key, payload=payload, timeout=timeout):
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        raise RuntimeError(f"{key}: {reply.err.payload.to_bytes().decode(errors='replace')}")
    raise RuntimeError(f"{key}: no reply within {timeout} s")


def get_status(session: zenoh.Session, car: str, service: str, timeout: float = 2.0) -> ServiceStatus:
    return decode(query(session, keys.status_key(car, service), timeout=timeout), ServiceStatus)


def query_message(session: zenoh.Session, car: str, service: str, leaf: str, payload: Any = None,
                  timeout: float = 2.0) -> Message | dict:
    """Call an extra queryable (reset, scenario...): JSON payload in, message or JSON out."""
    data = None if payload is None else json.dumps(payload).encode()
    raw = query(session, keys.service_key(car, service, leaf), data, timeout)
    try:
        return decode(raw)
    except ValueError:
        return json.loads(raw)
