"""Typed configuration: every default of the project lives here.

Sources, later wins: the defaults below, a TOML file (``--config``), then environment variables
``RACECAV_<SECTION>__<FIELD>`` (e.g. ``RACECAV_BUS__CAR=car1``; values are parsed as JSON when they
can be, so ``RACECAV_BUS__CONNECT='["tcp/10.0.0.2:7447"]'`` works). An invalid file or value
raises :class:`ConfigError` naming the field; the CLI turns it into exit code 2.

Each service owns one section. Physical car, world and lidar parameters are not configuration
of a run: they are data files read through :mod:`racecav.common.world`.
"""

from __future__ import annotations

import hashlib
import json
import os
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError


class Section(BaseModel):
    """Base of every section: unknown keys are errors (a typo must not be silently ignored)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class BusConfig(Section):
    """How a process joins the car's Zenoh network."""

    car: str = Field("car0", pattern=r"^[A-Za-z0-9_-]+$")
    """Car name: the second level of every key (racecav/<car>/...)."""
    connect: list[str] = ["tcp/127.0.0.1:7447"]
    """Router endpoints a service connects to (explicit: multicast scouting is off)."""
    mode: Literal["client", "peer"] = "client"
    """Services are clients of the car's router."""
    multicast_scouting: bool = False
    """Off by default: unreliable in containers and CI, and a security hole on the car."""
    user: str | None = None
    """Zenoh user/password login (the deployed router requires it)."""
    password: str | None = None
    tls_root_ca: Path | None = None
    """CA certificate that signed the router's certificate (tls/ endpoints)."""
    tls_cert: Path | None = None
    """Client certificate and key for mutual TLS."""
    tls_key: Path | None = None
    zenoh_config: Path | None = None
    """A full zenoh JSON5 config file to start from; the fields above are applied on top."""
    status_log_period_s: float = Field(5.0, gt=0)
    """Minimum period between two log lines about invalid input (rate limit)."""
    max_payload_bytes: int = Field(65536, gt=0)
    """Payloads larger than this are rejected before decoding."""


class RouterConfig(Section):
    """The car's router (``racecav router``)."""

    listen: list[str] = ["tcp/127.0.0.1:7447"]
    """Endpoints the router listens on. Add e.g. tls/0.0.0.0:7448 to reach it from the network."""
    config_file: Path | None = None
    """A zenoh JSON5 router config (access control, auth, TLS): see deploy/."""


class Config(Section):
    """The whole configuration. Sections are added by the services that own them."""

    bus: BusConfig = BusConfig()
    router: RouterConfig = RouterConfig()

    def digest(self) -> str:
        """Short hash of the effective configuration, reported in every ServiceStatus."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:12]


class ConfigError(Exception):
    """A configuration file or value is invalid; the message names the field."""


ENV_PREFIX = "RACECAV_"


def _env_overrides(environ: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(ENV_PREFIX) or "__" not in name:
            continue
        path = name[len(ENV_PREFIX):].lower().split("__")
        try:
            value: Any = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{name}: conflicts with another RACECAV_ variable")
        node[path[-1]] = value
    return out


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _merge(base[k], v)
        else:
            base[k] = v
    return base


def load_config(path: str | Path | None = None, environ: dict[str, str] | None = None) -> Config:
    """Load defaults <- TOML file <- RACECAV_* variables, validated.

    :param path: TOML file, or None for defaults (``RACECAV_CONFIG`` names one too).
    :param environ: environment to read (default ``os.environ``).
    :raises ConfigError: naming the file and the first invalid field.
    """
    environ = dict(os.environ if environ is None else environ)
    path = path or environ.get("RACECAV_CONFIG")
    data: dict[str, Any] = {}
    if path:
        try:
            data = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ConfigError(f"config file {path}: not found") from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"config file {path}: invalid TOML: {e}") from None
    data = _merge(data, _env_overrides(environ))
    try:
        return Config.model_validate(data)
    except ValidationError as e:
        lines = []
        for err in e.errors():
            field = ".".join(str(p) for p in err["loc"])
            lines.append(f"  {field}: {err['msg']} (got {err.get('input')!r})")
        src = f"config file {path}" if path else "configuration"
        raise ConfigError(f"{src} is invalid:\n" + "\n".join(lines)) from None
