"""``racecav deploy credentials [--dir D] [--tls]``: accounts, passwords and certificates of the car's bus.

Writes under D (default /etc/racecav):

- ``zenoh/passwords.txt``: the router's user/password dictionary (``user:password`` lines), one
  account per service (:data:`ACCOUNTS`); mode 0640 (the router, running as racecav, reads it);
- ``credentials/<account>.env``: ``RACECAV_BUS__USER`` / ``RACECAV_BUS__PASSWORD`` for that
  service's unit (``EnvironmentFile=``); mode 0600: systemd reads it as root before dropping
  privileges (the services share the racecav uid, so this separates accounts by role, not
  processes from each other: see docs/deploy.md);
- with ``--tls``: ``tls/ca.pem`` + ``ca.key`` (a local CA: move the key off the car once the
  certificates are made), ``tls/router.pem``/``.key`` (names from ``--host``), and for each
  account allowed off the car (sim, teleop, monitor) ``tls/<account>.pem``/``.key`` plus
  ``credentials/<account>-remote.toml``, a ``[bus]`` section for running that account from
  another machine over mutual TLS;
- ``zenoh/router.json5``: the router config rendered from deploy/zenoh/router.json5.

Existing passwords, keys and certificates are kept (re-running is safe); ``--force`` replaces them.
Certificates are made with the openssl command line: the ``cryptography`` package is not a
dependency of racecav, and openssl is on every Debian/Ubuntu/Jetson image.
"""

from __future__ import annotations

import argparse
import grp
import json
import os
import secrets
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

from racecav.common.config import Config

ACCOUNTS = ("sensor", "sim", "policy", "baseline", "actuator", "teleop", "monitor", "operator", "safety")
"""One Zenoh account per service (monitor: ``racecav state``/``echo``, read-only; teleop: a
joystick tool; operator: simulator control and the e-stop, e.g. ``racecav eval`` or a laptop).
What each may do is in deploy/zenoh/router.json5."""
REMOTE_ACCOUNTS = ("sim", "teleop", "monitor", "operator")
"""Accounts the router accepts from the network (mutual TLS); the others only over loopback."""

TEMPLATE = Path(__file__).parent / "zenoh" / "router.json5"
LOOPBACK = "tcp/127.0.0.1:7447"
TLS_PORT = 7448


def render_router_config(etc: Path, car: str, listen: list[str], tls: bool) -> str:
    """The router's JSON5 config for this car, from the template.

    :param etc: config directory holding zenoh/passwords.txt and tls/.
    :param listen: endpoints the router listens on.
    :param tls: keep the transport/link/tls section (needed by tls/ endpoints).
    """
    lines, keep = [], True
    for line in TEMPLATE.read_text().splitlines():
        if "@TLS-BEGIN" in line:
            keep = tls
        elif "@TLS-END" in line:
            keep = True
        elif keep:
            lines.append(line)
    text = "\n".join(lines) + "\n"
    return (text.replace("@LISTEN@", json.dumps(listen)).replace("@ETC@", str(etc))
            .replace("@CAR@", car))


def router_listen(tls: bool, port: int = TLS_PORT) -> list[str]:
    """Loopback for the car's own services; with TLS also every interface on ``port``."""
    return [LOOPBACK, f"tls/0.0.0.0:{port}"] if tls else [LOOPBACK]


class Plan:
    """What a deploy command does: each action is printed, and only done when not a dry run."""

    def __init__(self, dry_run: bool):
        self.dry_run = dry_run
        self.done: list[str] = []

    def note(self, what: str) -> None:
        self.done.append(what)
        print(("would " if self.dry_run else "") + what)

    def write(self, path: Path, text: str, mode: int, keep: bool = False, group: str | None = None) -> bool:
        """Write ``text`` to ``path`` with ``mode``; ``keep``: leave an existing file alone."""
        if keep and path.exists():
            print(f"kept {path} (exists)")
            return False
        self.note(f"write {path} (mode {mode:o}{', group ' + group if group else ''})")
        if not self.dry_run:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
            with os.fdopen(fd, "w") as f:
                f.write(text)
            os.chmod(path, mode)  # O_CREAT's mode is masked by the umask
            chgrp(path, group)
        return True

    def run(self, argv: list[str], **kw) -> None:
        self.note("run " + " ".join(map(str, argv)))
        if not self.dry_run:
            subprocess.run([str(a) for a in argv], check=True, **kw)


def chgrp(path: Path, group: str | None) -> None:
    """Give ``path`` to ``group`` if that group exists here (it does once install made the user)."""
    if group is None:
        return
    try:
        os.chown(path, -1, grp.getgrnam(group).gr_gid)
    except (KeyError, PermissionError):
        pass


def _passwords(path: Path, force: bool) -> dict[str, str]:
    """Existing user:password lines (kept unless ``force``), plus new ones for missing accounts."""
    out: dict[str, str] = {}
    if path.exists() and not force:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if line.strip():
                user, sep, pw = line.partition(":")
                if not sep or not user or not pw:
                    raise ValueError(f"{path}:{n}: expected user:password")
                out[user] = pw
    for acct in ACCOUNTS:
        out.setdefault(acct, secrets.token_urlsafe(24))  # no ':' or newline in urlsafe base64
    return out


def _openssl(plan: Plan, tls_dir: Path, name: str, cn: str, sans: list[str], force: bool, key_mode: int = 0o600,
             group: str | None = None) -> None:
    """Key + certificate ``name`` signed by the CA in ``tls_dir`` (EC P-256, serverAuth+clientAuth)."""
    key, pem = tls_dir / f"{name}.key", tls_dir / f"{name}.pem"
    if pem.exists() and key.exists() and not force:
        print(f"kept {pem} (exists)")
        return
    ext = ["basicConstraints=critical,CA:FALSE", "keyUsage=critical,digitalSignature,keyEncipherment",
           "extendedKeyUsage=serverAuth,clientAuth"]
    if sans:
        ext.append("subjectAltName=" + ",".join(sans))
    plan.note(f"make {pem} (CN={cn}{'; ' + ', '.join(sans) if sans else ''}) and {key} (mode {key_mode:o})")
    if plan.dry_run:
        return
    with tempfile.TemporaryDirectory() as tmp:
        csr, extfile = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        extfile.write_text("\n".join(ext) + "\n")
        _run_openssl(["req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                      "-keyout", key, "-out", csr, "-subj", f"/CN={cn}"])
        _run_openssl(["x509", "-req", "-in", csr, "-CA", tls_dir / "ca.pem", "-CAkey", tls_dir / "ca.key",
                      "-CAcreateserial", "-CAserial", Path(tmp) / "ca.srl", "-out", pem, "-days", "825",
                      "-extfile", extfile])
    os.chmod(key, key_mode)
    chgrp(key, group)


def _run_openssl(args: list) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise RuntimeError("openssl not found: install it (apt-get install openssl) or run without --tls")
    r = subprocess.run([exe, *map(str, args)], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed: {r.stderr.strip()}")


def default_hosts() -> list[str]:
    """Names the router's certificate is valid for: localhost, loopback and this machine's name."""
    name = socket.gethostname()
    return ["localhost", "127.0.0.1", name, f"{name}.local"]


def make_credentials(etc: Path, car: str, tls: bool, hosts: list[str] | None = None, force: bool = False,
                     dry_run: bool = False, group: str | None = "racecav", plan: Plan | None = None) -> Plan:
    """Create accounts (and with ``tls`` a CA and certificates) under ``etc``, then render the
    router config. Returns the plan (what was, or would be, done).

    :param etc: config directory (/etc/racecav on the car).
    :param hosts: DNS names / IPs in the router certificate (default :func:`default_hosts`).
    :param group: group owning the files the services read (the racecav user's group).
    """
    plan = plan or Plan(dry_run)
    pw_file = etc / "zenoh" / "passwords.txt"
    passwords = _passwords(pw_file, force)
    plan.write(pw_file, "".join(f"{u}:{p}\n" for u, p in sorted(passwords.items())), 0o640, group=group)
    for acct in ACCOUNTS:
        env = (f"# Zenoh login of racecav-{acct} (read by systemd as root: keep mode 600)\n"
               f"RACECAV_BUS__USER={acct}\nRACECAV_BUS__PASSWORD={passwords[acct]}\n")
        plan.write(etc / "credentials" / f"{acct}.env", env, 0o600)
    if tls:
        tls_dir = etc / "tls"
        new_ca = not (tls_dir / "ca.pem").exists() or force
        if new_ca:
            plan.note(f"make a local CA {tls_dir / 'ca.pem'} and {tls_dir / 'ca.key'} (mode 600)")
            if not plan.dry_run:
                tls_dir.mkdir(parents=True, exist_ok=True)
                _run_openssl(["req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                              "-keyout", tls_dir / "ca.key", "-out", tls_dir / "ca.pem", "-days", "3650",
                              "-subj", f"/CN=racecav {car} CA", "-addext", "basicConstraints=critical,CA:TRUE",
                              "-addext", "keyUsage=critical,keyCertSign,cRLSign"])
                os.chmod(tls_dir / "ca.key", 0o600)
        else:
            print(f"kept {tls_dir / 'ca.pem'} (exists)")
        sans = [("IP:" if _is_ip(h) else "DNS:") + h for h in (hosts or default_hosts())]
        # The router (user racecav) reads its own key: 640, group racecav.
        # A new CA invalidates every certificate signed by the old one: re-issue them all.
        _openssl(plan, tls_dir, "router", f"racecav-router-{car}", sans, new_ca, 0o640, group)
        for acct in REMOTE_ACCOUNTS:
            _openssl(plan, tls_dir, acct, acct, [], new_ca)
            host = next((h for h in (hosts or default_hosts()) if h not in ("localhost", "127.0.0.1")), "localhost")
            remote = (f"# {acct} on another machine: copy this file, tls/ca.pem, tls/{acct}.pem and tls/{acct}.key\n"
                      f"# there, fix the paths, and run e.g. `racecav --config {acct}-remote.toml state`.\n"
                      f"[bus]\ncar = {json.dumps(car)}\nconnect = [\"tls/{host}:{TLS_PORT}\"]\n"
                      f"user = {json.dumps(acct)}\npassword = {json.dumps(passwords[acct])}\n"
                      f"tls_root_ca = \"{tls_dir / 'ca.pem'}\"\ntls_cert = \"{tls_dir / (acct + '.pem')}\"\n"
                      f"tls_key = \"{tls_dir / (acct + '.key')}\"\n")
            plan.write(etc / "credentials" / f"{acct}-remote.toml", remote, 0o600)
    router = render_router_config(etc, car, router_listen(tls), tls)
    plan.write(etc / "zenoh" / "router.json5", router, 0o640, group=group)
    return plan


def _is_ip(host: str) -> bool:
    try:
        socket.inet_pton(socket.AF_INET6 if ":" in host else socket.AF_INET, host)
        return True
    except OSError:
        return False


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dir", default="/etc/racecav", help="config directory (default /etc/racecav)")
    p.add_argument("--tls", action="store_true", help="also a local CA and per-service certificates (mutual TLS)")
    p.add_argument("--host", action="append", help="name or IP the router certificate is valid for (repeatable)")
    p.add_argument("--force", action="store_true", help="replace existing passwords, keys and certificates")
    p.add_argument("--dry-run", action="store_true", help="print what would be done, do nothing")


def run(args: argparse.Namespace, cfg: Config) -> int:
    if not args.dry_run:  # before the first "write" line: a bad folder is one line, exit 2
        try:
            Path(args.dir).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            print(f"racecav deploy credentials: --dir {args.dir}: cannot create the folder ({e.strerror or e})")
            return 2
        if not os.access(args.dir, os.W_OK | os.X_OK):
            print(f"racecav deploy credentials: --dir {args.dir}: not writable by this user")
            return 2
    try:
        make_credentials(Path(args.dir), cfg.bus.car, args.tls, args.host, args.force, args.dry_run)
    except (RuntimeError, ValueError, OSError) as e:
        print(f"racecav deploy credentials: {e}")
        return 2  # a bad set-up (a folder that cannot be written...), like every other
    return 0
