"""Subcommand tables: a command's second level (``racecav bench NAME``, ``racecav deploy ACTION``,
``racecav emulate DEVICE``) as a name -> (module, help) table; each module exposes
``add_arguments(parser)`` and ``run(args, cfg)`` and keeps heavy imports inside ``run``."""

from __future__ import annotations

import argparse
import importlib


def add_table(p: argparse.ArgumentParser, dest: str, table: dict[str, tuple[str, str]], extra=None) -> None:
    """Second-level subcommands (``racecav bench NAME``, ``racecav deploy ACTION``...) from a
    name -> (module, help) table; ``extra(subparser)`` adds options common to all of them."""
    sub = p.add_subparsers(dest=dest, required=True, metavar=dest.upper())
    for name, (module, help_) in table.items():
        sp = sub.add_parser(name, help=help_, description=help_)
        if extra is not None:
            extra(sp)
        add_arguments_of(module, sp)


def run_table(args: argparse.Namespace, cfg, dest: str, table: dict[str, tuple[str, str]]) -> int:
    """Run the module :func:`add_table` chose for ``args.<dest>``."""
    return int(importlib.import_module(table[getattr(args, dest)][0]).run(args, cfg) or 0)


def add_arguments_of(module: str, p: argparse.ArgumentParser) -> None:
    # Argument definitions are cheap modules' functions; heavy imports stay inside run().
    importlib.import_module(module).add_arguments(p)
