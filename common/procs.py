"""Starting and stopping racecav processes: used by the benchmarks, the evaluation harness, the
demo and the tests, so that all of them run the real services the same way.

Every process started here is remembered; :func:`install_cleanup` (the ``racecav`` command calls
it for every subcommand) makes SIGTERM and SIGHUP raise SystemExit like SIGINT raises
KeyboardInterrupt, so ``finally`` blocks run, and stops whatever is still running at exit. A
bench, an evaluation or a demo killed with ``timeout``, Ctrl-C or ``systemctl stop``, or failing
with an exception, leaves no router or service behind holding its ports. (Children run in their
own sessions so that a Ctrl-C reaches them only through us, in order: clients before routers.)
A parent killed with SIGKILL runs no cleanup, so each child watches its parent instead
(:func:`exit_with_parent`): when it is gone the child stops itself the clean way, and so on down.
"""

from __future__ import annotations

import atexit
import os
import signal
import threading
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from typing import Iterator


_children: list[subprocess.Popen] = []
_lock = threading.Lock()
PARENT_ENV = "RACECAV_PARENT_PID"  # set by start(): the pid whose exit stops the child


def track(proc: subprocess.Popen) -> subprocess.Popen:
    """Remember ``proc`` (started in its own session) so that :func:`stop_all` stops it."""
    with _lock:
        _children[:] = [p for p in _children if p.poll() is None]
        _children.append(proc)
    return proc


def stop_all(timeout: float = 5.0) -> int:
    """Stop every remembered process still running, newest first (services before their
    router); returns how many there were."""
    with _lock:
        running = [p for p in reversed(_children) if p.poll() is None]
        _children.clear()
    for p in running:
        _signal(p, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    for p in running:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            _signal(p, signal.SIGKILL)
            p.wait()
    return len(running)


def _signal(p: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(p.pid, sig)
    except (ProcessLookupError, PermissionError):
        try:
            p.send_signal(sig)
        except ProcessLookupError:
            pass


def _raise_exit(signum, _frame):
    raise SystemExit(128 + signum)


def install_cleanup() -> None:
    """SIGTERM/SIGHUP -> SystemExit (so ``finally`` blocks run) and :func:`stop_all` at exit.
    A command that handles signals itself (every service) installs its own handlers after this."""
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, _raise_exit)
        # a command started in the background of a non-interactive shell inherits SIGINT ignored:
        # an explicit `kill -INT` must still stop it (and what it started)
        if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    atexit.register(stop_all)
    exit_with_parent()


def exit_with_parent(poll_s: float = 0.5) -> None:
    """In a process started by :func:`start`: SIGTERM to itself (its own clean shutdown, which
    stops what it started in turn) once the process that started it is gone, SIGKILLed included.
    A process started any other way (systemd, a shell) has no such parent and is left alone."""
    raw = os.environ.pop(PARENT_ENV, None)  # popped: what this process starts gets its own
    try:
        parent = int(raw) if raw else 0
    except ValueError:
        return
    if parent <= 1:
        return

    def watch() -> None:
        # orphans are re-parented (to init or a subreaper), so the parent pid changes
        while os.getppid() == parent:
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


CELL_ENV = "RACECAV_CELL"
"""Set by an evaluation cell on a Ray worker (evaluation/ray_cells.py): every process the cell
starts inherits it, so :func:`reap` finds them whoever their parent is now."""


def tagged(tag: str) -> list[int]:
    """Pids of the processes (other than this one) whose environment holds ``CELL_ENV=tag``."""
    want = f"{CELL_ENV}={tag}".encode()
    pids = []
    for d in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if not d.isdigit() or int(d) == os.getpid():
            continue
        try:
            with open(f"/proc/{d}/environ", "rb") as f:
                if want in f.read().split(b"\0"):
                    pids.append(int(d))
        except OSError:  # gone, or not ours to read
            continue
    return pids


def reap(tag: str, timeout: float = 5.0) -> int:
    """Stop every process tagged ``tag`` (SIGTERM to its group, then SIGKILL): what a cell left
    when its worker died (Ray ends only a worker's direct children, and only on a clean exit).
    Returns how many there were."""
    pids = tagged(tag)
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in pids:
            try:
                os.killpg(pid, sig) if os.getpgid(pid) == pid else os.kill(pid, sig)
            except (ProcessLookupError, PermissionError):
                pass
        deadline = time.monotonic() + timeout
        while (left := [p for p in pids if _alive(p)]) and time.monotonic() < deadline:
            time.sleep(0.05)
        if not left:
            break
    return len(pids)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has exited
    except OSError:
        return False


def free_port() -> int:
    """A TCP port on loopback that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def racecav_cmd(*args: str) -> list[str]:
    """Command line running ``racecav ARGS`` with this interpreter (works without the script on PATH)."""
    return [sys.executable, "-m", "racecav.cli", *args]


def bus_env(endpoint: str, car: str = "car0", extra: dict[str, str] | None = None) -> dict[str, str]:
    """Environment that points a racecav process at ``endpoint``."""
    env = dict(os.environ)
    env["RACECAV_BUS__CONNECT"] = f'["{endpoint}"]'
    env["RACECAV_BUS__CAR"] = car
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


def start(args: list[str], env: dict[str, str], log_path=None) -> subprocess.Popen:
    """Start ``racecav ARGS`` in its own process group; output to ``log_path`` or inherited."""
    out = open(log_path, "ab") if log_path else None
    env = {**env, PARENT_ENV: str(os.getpid())}
    return track(subprocess.Popen(racecav_cmd(*args), env=env, stdout=out,
                                  stderr=subprocess.STDOUT if out else None, start_new_session=True))


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGTERM (clean shutdown), then SIGKILL if it does not exit in time."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode


def wait_alive(session, car: str, service: str, timeout: float = 30.0, proc: subprocess.Popen | None = None) -> None:
    """Block until ``service`` holds its liveliness token; raise if it dies or times out.

    With ``proc``: until that process answers the status query. A token of the same name may
    still be the previous instance's (killed, and the router has not yet dropped it)."""
    from racecav.common.client import get_status, live_services

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"{service} exited with code {proc.returncode} before joining the bus")
        if service in live_services(session, car, timeout=0.5):
            if proc is None:
                return
            try:
                if get_status(session, car, service, timeout=0.5).pid == proc.pid:
                    return
            except RuntimeError:  # no status reply yet
                pass
        time.sleep(0.1)
    raise TimeoutError(f"{service} not alive on car {car} after {timeout} s")


def start_router(port: int | None = None, log_path=None) -> tuple[subprocess.Popen, str]:
    """Start ``racecav router`` on a free loopback port and wait until it is on the bus;
    returns the process and its endpoint (stop it with :func:`stop`)."""
    port = port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = bus_env(endpoint, extra={"RACECAV_ROUTER__LISTEN": f'["{endpoint}"]'})
    proc = start(["router"], env, log_path)
    try:
        deadline = time.monotonic() + 20
        while True:  # the router is up when its port accepts connections
            if proc.poll() is not None:
                raise RuntimeError(f"router exited with code {proc.returncode}")
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise TimeoutError("router did not start") from None
                time.sleep(0.05)
        # ...and it is on the bus when its own liveliness token is visible to a client.
        from racecav.common.client import open_session
        from racecav.common.config import load_config

        with open_session(load_config(environ={"RACECAV_BUS__CONNECT": f'["{endpoint}"]'})) as s:
            wait_alive(s, "car0", "router", timeout=20, proc=proc)
    except BaseException:
        stop(proc)
        raise
    return proc, endpoint


@contextmanager
def router(port: int | None = None, log_path=None) -> Iterator[str]:
    """Run ``racecav router`` on a free loopback port; yields its endpoint."""
    proc, endpoint = start_router(port, log_path)
    try:
        yield endpoint
    finally:
        stop(proc)
