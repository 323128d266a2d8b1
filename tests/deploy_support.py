"""A deployed car in a temporary root, its units run as plain processes (no systemd as PID 1 here).

``DeployedCar`` runs ``racecav deploy install --root TMP --venv <this venv>``, points the
installed racecav.env at free loopback ports and emulated devices (the documented way to
override the config), then starts each unit's ExecStart line with the environment systemd would
give it (Environment=, EnvironmentFile=, NOTIFY_SOCKET, WATCHDOG_USEC), in the unit's working
directory with its state/cache directories created, as systemd does.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

from racecav.common import procs
from racecav.common.config import load_config
from racecav.deploy.credentials import REMOTE_ACCOUNTS
from racecav.deploy.install import Layout, install
from racecav.deploy.units import read_env_file, service_command


def ensure_tool(exe: str, package: str) -> str:
    """Path of ``exe``; installs the Debian/Ubuntu ``package`` (as root, with apt-get) if missing.

    Skips the calling test, loudly, only when that is impossible.
    """
    import shutil

    import pytest

    path = shutil.which(exe)
    if path is None and shutil.which("apt-get") and os.geteuid() == 0:
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        subprocess.run(["apt-get", "update", "-qq"], env=env, check=False, capture_output=True)
        subprocess.run(["apt-get", "install", "-y", "-qq", "--no-install-recommends", package], env=env,
                       check=False, capture_output=True)
        path = shutil.which(exe)
    if path is None:
        pytest.skip(f"SKIPPED LOUDLY: {exe} is missing and could not be installed (package {package}; "
                    "needs root and apt-get): this deployment check did NOT run")
    return path


def wait_until(pred, timeout=10.0, step=0.05) -> bool:
    """True once ``pred()`` is; False after ``timeout`` s. A status query that got no answer in
    time (RuntimeError from the client helpers, e.g. on a loaded CI machine) counts as not yet."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if pred():
                return True
        except RuntimeError:
            pass
        time.sleep(step)
    return False


class Notify:
    """A systemd notification socket (abstract namespace): what the units' Type=notify reads."""

    def __init__(self, name: str):
        self.addr = f"@racecav-test-{os.getpid()}-{name}-{time.monotonic_ns()}"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind("\0" + self.addr[1:])
        self.sock.settimeout(0.2)
        self.messages: list[tuple[float, str]] = []

    def poll(self) -> list[str]:
        while True:
            try:
                self.messages.append((time.monotonic(), self.sock.recv(4096).decode()))
            except (socket.timeout, BlockingIOError):
                return [m for _, m in self.messages]

    def close(self) -> None:
        self.sock.close()


class DeployedCar:
    """Install into ``root`` and run units from it.

    :param extra_env: lines added to the installed racecav.env (KEY -> value).
    """

    def __init__(self, root: Path, extra_env: dict[str, str] | None = None, car: str = "car0",
                 hosts: list[str] | None = None):
        self.root, self.car = root, car
        ensure_tool("openssl", "openssl")  # the credentials' certificates
        self.lay = Layout(root=root, venv=sys.prefix)
        install(self.lay, car=car, tls=True, systemctl=False, hosts=hosts)
        self.port, self.tls_port = procs.free_port(), procs.free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        env = {"RACECAV_BUS__CONNECT": f'["{self.endpoint}"]',
               "RACECAV_ROUTER__LISTEN": f'["{self.endpoint}", "tls/0.0.0.0:{self.tls_port}"]',
               **(extra_env or {})}
        with open(self.lay.etc / "racecav.env", "a") as f:
            for k, v in env.items():
                f.write(f"{k}='{v}'\n")
        self.procs: dict[str, subprocess.Popen] = {}
        self.notify: dict[str, Notify] = {}
        self.logs = root / "logs"
        self.logs.mkdir(exist_ok=True)

    def unit(self, name: str) -> Path:
        return self.lay.unit_dir / f"racecav-{name}.service"

    def command(self, name: str, key: str = "ExecStart") -> tuple[list[str], dict[str, str]]:
        """argv (of ExecStart or ``key``) and environment of racecav-<name>.service, with the
        unit's state/cache directories under the root."""
        if name in self.notify:
            self.notify[name].close()
        notify = self.notify[name] = Notify(name)
        argv, env = service_command(self.unit(name), {"PATH": os.environ.get("PATH", "/usr/bin:/bin"),
                                                      "NOTIFY_SOCKET": notify.addr}, key)
        svc_watchdog = self._unit_value(name, "WatchdogSec")
        env["WATCHDOG_USEC"] = str(int(float(svc_watchdog) * 1e6))
        for k, v in env.items():  # StateDirectory=/CacheDirectory= live under the root here
            if v.startswith(("/var/lib/racecav", "/var/cache/racecav")):
                env[k] = str(self.root / v.lstrip("/"))
        return argv, env

    def _unit_value(self, name: str, key: str) -> str:
        from racecav.deploy.units import parse_unit

        return parse_unit(self.unit(name))["Service"][key][-1]

    def start(self, name: str) -> subprocess.Popen:
        """Start racecav-<name>.service's ExecStart as a process (its own process group)."""
        argv, env = self.command(name)
        wd = self.root / "var/lib/racecav"
        wd.mkdir(parents=True, exist_ok=True)
        log = open(self.logs / f"{name}-{len([k for k in self.procs if k.startswith(name)])}.log", "ab")
        p = subprocess.Popen(argv, env=env, cwd=wd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs[name] = p
        return p

    def run_command(self, name: str, key: str, timeout: float = 60.0) -> int:
        """Run the unit's ``key`` command (e.g. ExecStopPost) to completion; its exit code."""
        argv, env = self.command(name, key)
        env.pop("NOTIFY_SOCKET")
        env.pop("WATCHDOG_USEC")
        with open(self.logs / f"{name}-{key}.log", "ab") as log:
            return subprocess.run(argv, env=env, stdout=log, stderr=subprocess.STDOUT, timeout=timeout).returncode

    def wait_ready(self, name: str, timeout: float = 60.0) -> None:
        """Until the unit's process sent READY=1 (what systemd waits for with Type=notify)."""
        p, n = self.procs[name], self.notify[name]
        if not wait_until(lambda: "READY=1" in n.poll() or p.poll() is not None, timeout):
            raise TimeoutError(f"{name}: no READY=1 within {timeout} s\n{self.log(name)}")
        if p.poll() is not None:
            raise RuntimeError(f"{name} exited with {p.returncode}\n{self.log(name)}")

    def log(self, name: str) -> str:
        return "\n".join(f.read_text(errors="replace")[-3000:] for f in sorted(self.logs.glob(f"{name}-*.log")))

    def stop(self, name: str) -> int:
        return procs.stop(self.procs[name])

    def stop_all(self) -> None:
        for name in reversed(list(self.procs)):
            procs.stop(self.procs[name])
        for n in self.notify.values():
            n.close()

    def account_env(self, account: str) -> dict[str, str]:
        return read_env_file(self.lay.etc / "credentials" / f"{account}.env")

    def client_config(self, account: str | None, tls: bool | str = False, cert: bool | str = True, **bus):
        """Config of a client: ``account``'s login (None: no login), over loopback tcp or TLS.

        :param tls: True: tls/localhost; a string: that host (e.g. a non-loopback address).
        :param cert: True: the account's own client certificate (monitor's if it has none); a
            string: that account's certificate; False: none.
        """
        env = {"RACECAV_CONFIG": str(self.lay.etc / "racecav.toml"), **read_env_file(self.lay.etc / "racecav.env")}
        env.pop("RACECAV_ROUTER__LISTEN", None)
        if account:
            env.update(self.account_env(account))
        cfg = load_config(environ=env)
        upd = dict(bus)
        if tls:
            tls_dir = self.lay.etc / "tls"
            host = tls if isinstance(tls, str) else "localhost"
            upd.update(connect=[f"tls/{host}:{self.tls_port}"], tls_root_ca=tls_dir / "ca.pem")
            if cert:
                who = cert if isinstance(cert, str) else account if account in REMOTE_ACCOUNTS else "monitor"
                upd.update(tls_cert=tls_dir / f"{who}.pem", tls_key=tls_dir / f"{who}.key")
        return cfg.model_copy(update={"bus": cfg.bus.model_copy(update=upd)})

    def session(self, account: str | None, **kw):
        from racecav.common.client import open_session

        return open_session(self.client_config(account, **kw))
