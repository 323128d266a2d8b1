"""`racecav emulate rplidar|vesc`: byte-exact device emulators on a pty, to run the stack without hardware.

Each prints the path to open (a symlink to its pty) on its first line, e.g.::

    racecav emulate rplidar &      # -> /tmp/racecav-rplidar
    racecav sensor --port /tmp/racecav-rplidar
    racecav emulate vesc --log /tmp/vesc.jsonl &
    racecav actuator --port /tmp/racecav-vesc
"""

from __future__ import annotations

import argparse
import sys

from racecav.common.subcommands import add_table, run_table

DEVICES = {
    "rplidar": ("racecav.services.sensor.emulator", "RPLIDAR S2 (info/health/conf, standard/express/dense scans, faults)"),
    "vesc": ("racecav.services.actuator.emulator", "VESC (records every frame, answers GET_VALUES, motor model)"),
    "record-scans": ("racecav.services.sensor.record_scans", "save Scans from the bus (e.g. the simulator's) for `rplidar --replay`"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_table(p, "device", DEVICES)


def run(args: argparse.Namespace, cfg) -> int:
    try:
        return run_table(args, cfg, "device", DEVICES)
    except OSError as e:  # e.g. --link into a missing directory: one line, no traceback
        where = f"--link {args.link}" if getattr(args, "link", None) else (e.filename2 or e.filename or "")
        print(f"racecav emulate {args.device}: {where}: {e.strerror or e}", file=sys.stderr)
        return 2
