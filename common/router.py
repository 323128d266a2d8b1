"""``racecav router``: the car's Zenoh router, run in-process by the zenoh Python package.

No zenohd package exists on PyPI or in Debian; the Python package can act as a router itself
(mode "router"). To use a system zenohd instead, run ``zenohd -c /etc/racecav/zenoh/router.json5``
(the secured config rendered by ``racecav deploy credentials``; docs/deploy.md) (or
``zenohd -l tcp/127.0.0.1:7447 --no-multicast-scouting``) and do not start this command: services
only need an endpoint in ``bus.connect``.

The router is itself a service: it holds racecav/<car>/router/alive and answers status, so
``racecav state`` shows whether the car's router is up.
"""

from __future__ import annotations

import argparse

from racecav.common.bus import Service
from racecav.common.config import Config


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", action="append", help="endpoint to listen on (repeatable; default: router.listen)")


def run(args: argparse.Namespace, cfg: Config) -> int:
    listen = args.listen or cfg.router.listen
    svc = Service(cfg, "router", mode="router", listen=listen, zenoh_config_file=cfg.router.config_file)
    svc.log.info("listening on %s", ", ".join(listen))
    return svc.run()
