"""Shared fixtures: a real Zenoh router on a free loopback port, and racecav processes on it."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from racecav.common import procs
from racecav.common.config import load_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def router(tmp_path) -> str:
    """Endpoint of a fresh ``racecav router`` process (stopped after the test)."""
    with procs.router(log_path=tmp_path / "router.log") as endpoint:
        yield endpoint


@pytest.fixture
def bus_cfg(router):
    """Config of a client on the test's router."""
    return load_config(environ={"RACECAV_BUS__CONNECT": f'["{router}"]'})


@pytest.fixture
def session(bus_cfg):
    """A client Zenoh session on the test's router."""
    from racecav.common.client import open_session

    s = open_session(bus_cfg)
    yield s
    s.close()


@pytest.fixture
def spawn(router, tmp_path):
    """``spawn(*racecav_args, env=None)`` starts a racecav process on the router; all are
    stopped (SIGTERM, then SIGKILL) after the test. Logs are in tmp_path."""
    started: list[subprocess.Popen] = []

    def _spawn(*args: str, env: dict | None = None) -> subprocess.Popen:
        log = tmp_path / f"{args[0]}-{len(started)}.log"
        # the actuator's e-stop latch file: per test, never the user's (tests run concurrently)
        env = {"RACECAV_ACTUATOR__STATE_DIR": str(tmp_path / "state"), **(env or {})}
        p = procs.start(list(args), procs.bus_env(router, extra=env), log)
        p.log_path = log  # type: ignore[attr-defined]
        started.append(p)
        return p

    yield _spawn
    for p in started:
        procs.stop(p)
