"""``racecav echo TOPIC``: print the messages of a key, decoded and validated (like
``ros2 topic echo``). It is a service like any other: invalid payloads are counted, not fatal,
and ``racecav state echo`` shows its counters."""

from __future__ import annotations

import argparse
import json

from racecav.common.bus import Service
from racecav.common.config import Config
from racecav.common.messages import MESSAGE_TYPES


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("topic", help="topic under racecav/<car>/ (scan, cmd, state, obstacles) or a full key")
    p.add_argument("--type", choices=sorted(MESSAGE_TYPES), help="message type (default: guessed from the topic)")
    p.add_argument("--name", default="echo", help="service name (several echos need different names)")
    p.add_argument("--count", type=int, default=0, help="exit after this many messages (0: run until stopped)")
    p.add_argument("--quiet", action="store_true", help="count only, print nothing")


class Echo(Service):
    def __init__(self, cfg: Config, args: argparse.Namespace):
        super().__init__(cfg, args.name)
        self.key = args.topic if "/" in args.topic else self.topic(args.topic)
        self.cls = MESSAGE_TYPES[args.type or args.topic.rsplit("/", 1)[-1]]
        self.count, self.quiet, self.seen = args.count, args.quiet, 0

    def setup(self) -> None:
        self.box = self.inbox(self.key, self.cls)

    def step(self) -> None:
        msg = self.box.take(timeout=0.2)
        if msg is None:
            return
        self.seen += 1
        if not self.quiet:
            print(json.dumps(msg.model_dump(mode="json")), flush=True)
        if self.count and self.seen >= self.count:
            self.request_stop()

    def info(self) -> dict:
        return {"key": self.key, "type": self.cls.TYPE, "printed": self.seen}


def run(args: argparse.Namespace, cfg: Config) -> int:
    if args.type is None and args.topic.rsplit("/", 1)[-1] not in MESSAGE_TYPES:
        raise SystemExit(f"racecav echo: cannot guess the type of {args.topic!r}: pass --type")
    return Echo(cfg, args).run()
