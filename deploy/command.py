"""``racecav deploy install|credentials``: put racecav on the car (docs/deploy.md)."""

from __future__ import annotations

import argparse

from racecav.common.subcommands import add_table, run_table

ACTIONS = {
    "install": ("racecav.deploy.install", "venv, systemd units, udev rules, default config, credentials"),
    "credentials": ("racecav.deploy.credentials", "bus accounts and passwords, with --tls a local CA and certificates"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_table(p, "action", ACTIONS)


def run(args: argparse.Namespace, cfg) -> int:
    return run_table(args, cfg, "action", ACTIONS)
