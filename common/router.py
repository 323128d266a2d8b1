"""``racecav router``: the car's Zenoh router, run in-process by the zenoh Python package.

No zenohd package exists on PyPI or in Debian; the Python package can act as a router itself
(mode "router"). To use a system zenohd instead, run ``zenohd -c /etc/racecav/zenoh/router.json5``
(the secured config rendered by ``racecav deploy credentials``; docs/deploy.md) (or
``zenohd -l tcp/127.0.0.1:7447 --no-multicast-scouting``) and do not start this command: services
only need an endpoint in ``bus.connect``.

The router is itself a service: it holds racecav/<car>/router/alive and answers status, so
``racecav state`` shows whether the car's router is up. It also keeps the e-stop latch
(racecav/<car>/estop: any payload latches, exactly ``clear`` clears) and answers it on
racecav/<car>/router/estop, so an e-stop published while the actuator is down takes effect
when the actuator starts (:mod:`racecav.common.estop`; with zenohd only the actuator's latch
file remains).
"""

from __future__ import annotations

import argparse
import time

from racecav.common.bus import Service
from racecav.common.config import Config
from racecav.common.estop import is_clear
from racecav.common.keys import ESTOP


class RouterService(Service):
    """The router plus the e-stop latch's second copy."""

    def setup(self) -> None:
        self.log.info("listening on %s", ", ".join(self._listen or []))
        self.estop_latched = False
        self.estop_changed = 0.0
        self.estop_count = 0
        self.subscribe(self.topic(ESTOP), None, self._on_estop)
        self.queryable("estop", lambda _p: {"latched": self.estop_latched, "since_s": self.estop_changed,
                                            "count": self.estop_count})

    def _on_estop(self, raw: bytes) -> None:
        self.estop_count += 1
        latched = not is_clear(raw)
        if latched != self.estop_latched:
            self.estop_latched, self.estop_changed = latched, time.monotonic()
            self.log.warning("e-stop %s", "latched" if latched else "cleared")

    def info(self) -> dict:
        return {"estop": self.estop_latched}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", action="append", help="endpoint to listen on (repeatable; default: router.listen)")


def run(args: argparse.Namespace, cfg: Config) -> int:
    listen = args.listen or cfg.router.listen
    svc = RouterService(cfg, "router", mode="router", listen=listen, zenoh_config_file=cfg.router.config_file)
    return svc.run()
