"""``racecav deploy install [--prefix P] [--root R] [--dry-run]``: put racecav on the car.

What it does, in order (each step is printed; ``--dry-run`` prints without doing):

1. the system user ``racecav`` (group racecav, member of dialout for the serial devices);
2. a venv at ``PREFIX/venv`` with racecav installed from ``--source`` (skip with ``--venv PATH``
   to use an existing one);
3. the systemd units racecav-{router,sensor,sim,policy,baseline,actuator,safety}.service and
   racecav.target into ``/etc/systemd/system`` (paths rewritten for the venv and the root);
4. the udev rules (/dev/rplidar, /dev/vesc) into ``/etc/udev/rules.d``;
5. ``/etc/racecav/racecav.toml`` and ``racecav.env`` (kept if they exist: they are yours);
6. the bus's accounts, passwords, TLS certificates and router config (``racecav deploy
   credentials``; TLS unless ``--no-tls``);
7. ``systemctl daemon-reload``, enable racecav.target with router, sensor, policy and actuator,
   and reload udev: only when installing into / as root (``--no-systemctl`` skips it).

``--root R`` installs the whole tree under R with every path inside the files pointing into R
(a self-contained install for tests, containers, or an image being built); default "/".
"""

from __future__ import annotations

import argparse
import os
import pwd
import shutil
import sys
from pathlib import Path

from racecav.common.config import Config
from racecav.deploy.credentials import Plan, make_credentials, router_listen

HERE = Path(__file__).resolve().parent
SERVICES = ("router", "sensor", "sim", "policy", "baseline", "actuator", "safety")
"""Every unit racecav-<name>.service; :data:`ENABLED` are the real car's defaults (safety, the
emergency-brake supervisor, is optional: ``systemctl enable --now racecav-safety``)."""
ENABLED = ("router", "sensor", "policy", "actuator")
USER = "racecav"
UNIT_VENV = "/opt/racecav/venv"
"""The venv path as spelled in the unit files of the repository."""


def unit_files() -> list[Path]:
    return [HERE / "systemd" / f"racecav-{s}.service" for s in SERVICES] + [HERE / "systemd" / "racecav.target"]


class Layout:
    """Where things go. Every path inside the installed files is under ``root`` too.

    :param root: install root ("/" on the car).
    :param prefix: where the venv lives (relative to root).
    :param venv: an existing venv to use instead of PREFIX/venv (absolute, not re-rooted).
    """

    def __init__(self, root: str | Path = "/", prefix: str | Path = "/opt/racecav", venv: str | Path | None = None):
        self.root = Path(root)
        self.prefix = self._in_root(prefix)
        self.venv = Path(venv) if venv else self.prefix / "venv"
        self.etc = self._in_root("/etc/racecav")
        self.unit_dir = self._in_root("/etc/systemd/system")
        self.udev_dir = self._in_root("/etc/udev/rules.d")

    def _in_root(self, p: str | Path) -> Path:
        return self.root / str(p).lstrip("/")

    @property
    def system(self) -> bool:
        """Installing into the running system (not a separate tree)."""
        return self.root.resolve() == Path("/")


def render_unit(text: str, lay: Layout) -> str:
    """A repository unit with the venv and /etc/racecav paths of this layout."""
    return text.replace(UNIT_VENV, str(lay.venv)).replace("/etc/racecav", str(lay.etc))


def render_config(lay: Layout, car: str, tls: bool) -> str:
    """The default /etc/racecav/racecav.toml for this layout."""
    import json

    text = (HERE / "config" / "racecav.toml").read_text()
    return (text.replace("@CAR@", car).replace("@LISTEN@", json.dumps(router_listen(tls)))
            .replace("@ETC@", str(lay.etc)))


def _user_exists(name: str) -> bool:
    try:
        pwd.getpwnam(name)
        return True
    except KeyError:
        return False


def install(lay: Layout, car: str = "car0", tls: bool = True, source: Path | None = None,
            systemctl: bool = True, dry_run: bool = False, hosts: list[str] | None = None) -> Plan:
    """Install into ``lay``; returns the plan (what was, or would be, done).

    :param hosts: names/IPs for the router's TLS certificate (default: localhost, this host's name).
    """
    plan = Plan(dry_run)
    system = systemctl and lay.system and (dry_run or os.geteuid() == 0)
    # 1. user
    if system and not _user_exists(USER):
        plan.run(["useradd", "--system", "--user-group", "--groups", "dialout", "--home-dir", "/var/lib/racecav",
                  "--no-create-home", "--shell", "/usr/sbin/nologin", USER])
    elif not system:
        print(f"skip the {USER} user (not installing into the running system as root)")
    # 2. venv
    if lay.venv == lay.prefix / "venv":
        src = source or HERE.parent
        if not (src / "pyproject.toml").exists():
            raise RuntimeError(f"--source {src}: no pyproject.toml (give the racecav source tree)")
        plan.run([sys.executable, "-m", "venv", lay.venv])
        plan.run([lay.venv / "bin" / "pip", "install", "--quiet", src])
    elif not (lay.venv / "bin" / "racecav").exists():
        raise RuntimeError(f"--venv {lay.venv}: no bin/racecav in it")
    else:
        print(f"use the existing venv {lay.venv}")
    # 3-4. units, udev rules
    for f in unit_files():
        plan.write(lay.unit_dir / f.name, render_unit(f.read_text(), lay), 0o644)
    plan.write(lay.udev_dir / "99-racecav.rules", (HERE / "udev" / "99-racecav.rules").read_text(), 0o644)
    # 5. configuration (yours once written)
    plan.write(lay.etc / "racecav.toml", render_config(lay, car, tls), 0o644, keep=True)
    plan.write(lay.etc / "racecav.env", (HERE / "config" / "racecav.env").read_text(), 0o644, keep=True)
    # 6. accounts, certificates, router config
    make_credentials(lay.etc, car, tls, hosts, plan=plan, group=USER)
    # 7. systemd and udev
    if system:
        plan.run(["systemctl", "daemon-reload"])
        plan.run(["systemctl", "enable", "racecav.target", *(f"racecav-{s}.service" for s in ENABLED)])
        if shutil.which("udevadm"):
            plan.run(["udevadm", "control", "--reload-rules"])
            plan.run(["udevadm", "trigger", "--subsystem-match=tty"])
        print("next: systemctl start racecav.target; racecav state "
              f"(as root, or with RACECAV_CONFIG={lay.etc}/racecav.toml and the monitor login)")
    else:
        print("skip systemctl/udevadm (not installing into the running system as root)")
    return plan


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--prefix", default="/opt/racecav", help="where the venv goes (default /opt/racecav)")
    p.add_argument("--root", default="/", help="install root; every path inside the files is under it too")
    p.add_argument("--venv", help="use this existing venv instead of creating PREFIX/venv")
    p.add_argument("--source", type=Path, help="racecav source tree to pip install (default: this one)")
    p.add_argument("--car", help="car name (default: bus.car)")
    p.add_argument("--no-tls", action="store_true", help="no TLS endpoint, no certificates (loopback only)")
    p.add_argument("--host", action="append", help="name or IP the router certificate is valid for (repeatable; "
                   "default: localhost, 127.0.0.1 and this machine's name)")
    p.add_argument("--no-systemctl", action="store_true", help="do not create the user or call systemctl/udevadm")
    p.add_argument("--dry-run", action="store_true", help="print what would be done, do nothing")


def run(args: argparse.Namespace, cfg: Config) -> int:
    lay = Layout(args.root, args.prefix, args.venv)
    try:
        plan = install(lay, args.car or cfg.bus.car, not args.no_tls, args.source, not args.no_systemctl,
                       args.dry_run, args.host)
    except (RuntimeError, OSError) as e:
        print(f"racecav deploy install: {e}", file=sys.stderr)
        return 1
    print(f"{'would do' if args.dry_run else 'did'} {len(plan.done)} step(s)")
    return 0
