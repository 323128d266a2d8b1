"""Read an installed racecav unit the way systemd does: its ExecStart and its environment.

Used by the tests (CI has no systemd as PID 1, so they start each unit's ExecStart line as a
plain process with the environment systemd would give it) and handy on a machine without
systemd (containers): ``racecav deploy`` never needs it on the car.
"""

from __future__ import annotations

import shlex
from pathlib import Path


def parse_unit(path: str | Path) -> dict[str, dict[str, list[str]]]:
    """Sections -> keys -> values in file order (a key may repeat, e.g. Environment=).

    :raises ValueError: naming the line that is neither a section, a comment nor key=value.
    """
    out: dict[str, dict[str, list[str]]] = {}
    section = None
    lines = Path(path).read_text().splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        n = i + 1
        while line.endswith("\\") and i + 1 < len(lines):  # continuation lines
            i += 1
            line = line[:-1] + " " + lines[i].strip()
        i += 1
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            out.setdefault(section, {})
            continue
        key, sep, value = line.partition("=")
        if not sep or section is None:
            raise ValueError(f"{path}:{n}: expected [Section] or Key=Value, got {line!r}")
        out[section].setdefault(key.strip(), []).append(value.strip())
    return out


def read_env_file(path: str | Path) -> dict[str, str]:
    """KEY=VALUE lines as systemd's EnvironmentFile= reads them (comments, quotes stripped)."""
    env: dict[str, str] = {}
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line[0] in "#;":
            continue
        key, sep, value = line.partition("=")
        if not sep or not key.strip().isidentifier():
            raise ValueError(f"{path}:{n}: expected KEY=VALUE, got {line!r}")
        value = value.strip()
        if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
            value = value[1:-1]
        env[key.strip()] = value
    return env


def service_command(unit: str | Path, base_env: dict[str, str] | None = None,
                    key: str = "ExecStart") -> tuple[list[str], dict[str, str]]:
    """The argv of ExecStart= (or ``key``, e.g. ExecStopPost) and the environment systemd would
    start it with.

    Environment= first, then each EnvironmentFile= in order (they override Environment=, as
    documented in systemd.exec(5)); a leading "-" marks an optional file (and, on a command,
    a failure that is ignored).

    :param base_env: the environment to start from (systemd's own: PATH, NOTIFY_SOCKET, ...).
    """
    svc = parse_unit(unit).get("Service", {})
    env = dict(base_env or {})
    for assignments in svc.get("Environment", []):
        for a in shlex.split(assignments):
            k, _, v = a.partition("=")
            env[k] = v
    for f in svc.get("EnvironmentFile", []):
        optional = f.startswith("-")
        path = Path(f.lstrip("-"))
        if optional and not path.exists():
            continue
        env.update(read_env_file(path))
    lines = svc.get(key, [])
    if len(lines) != 1:
        raise ValueError(f"{unit}: expected one {key}=, found {len(lines)}")
    return shlex.split(lines[0].lstrip("-")), env
