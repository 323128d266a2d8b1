"""``racecav deploy install|credentials``: put racecav on the car (docs/deploy.md)."""

from __future__ import annotations

import argparse
import importlib

ACTIONS = {
    "install": ("racecav.deploy.install", "venv, systemd units, udev rules, default config, credentials"),
    "credentials": ("racecav.deploy.credentials", "bus accounts and passwords, with --tls a local CA and certificates"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    for name, (module, help_) in ACTIONS.items():
        sp = sub.add_parser(name, help=help_, description=help_)
        importlib.import_module(module).add_arguments(sp)


def run(args: argparse.Namespace, cfg) -> int:
    return importlib.import_module(ACTIONS[args.action][0]).run(args, cfg)
