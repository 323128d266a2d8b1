"""The ``racecav`` command: one subcommand per service and tool.

Subcommands are imported lazily so that ``racecav state`` does not pay for torch or pybullet.
A subcommand module exposes ``add_arguments(parser)`` and ``run(args, cfg) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from racecav.common.config import ConfigError, load_config
from racecav.common.subcommands import add_arguments_of

# name -> (module, one-line help). Keep sorted by role: infrastructure, services, tools.
COMMANDS: dict[str, tuple[str, str]] = {
    "router": ("racecav.common.router", "run the car's Zenoh router in-process (mode router)"),
    "state": ("racecav.common.state", "list live services and their status (any Zenoh client can do this)"),
    "echo": ("racecav.common.echo", "print decoded messages of a key, like `ros2 topic echo`"),
    "bench": ("racecav.common.bench", "benchmarks: results go to docs/benchmarks.md"),
    "demo": ("racecav.evaluation.demo", "the README's main command"),
    "suite": ("racecav.evaluation.suite_cli", "generate the procedural conflict suite (train/test splits of scenario files)"),
    "eval": ("racecav.evaluation.evaluate", "evaluation over the real services: success, distances, latency; --table writes docs/results.md"),
    "sensor": ("racecav.services.sensor.service", "real lidar: RPLIDAR S2 driver publishing 170-ray Scans"),
    "actuator": ("racecav.services.actuator.service", "VESC motor and steering from DriveCommands, with watchdog and e-stop"),
    "emulate": ("racecav.services.emulate", "device emulators on a pty: rplidar | vesc"),
    "sim": ("racecav.services.sim.service", "PyBullet world playing the car: Scan/state out, DriveCommand in (realtime or lockstep)"),
    "train": ("racecav.training.cli", "PPO training of the racing/overtaking policies (resumable), checkpoint selection, shipping, report"),
    "deploy": ("racecav.deploy.command", "install on the car (venv, systemd units, udev, config) and make bus credentials"),
    "scripted": ("racecav.services.sim.scripted", "controller answering each scan with a scripted command program (tests, demos)"),
    "policy": ("racecav.services.policy.service", "DRL policy controller: newest Scan -> numpy MLP -> DriveCommand"),
    "baseline": ("racecav.services.baseline.service", "MPC-APF baseline controller: lidar obstacles + casadi MPC -> DriveCommand"),
    "safety": ("racecav.services.safety.service", "emergency-brake supervisor: per-ray time to collision -> brake input of the mux (racecav/<car>/safety)"),
    "ros2": ("racecav.services.ros2.service", "ROS 2 mirror over Zenoh (rmw_zenoh or zenoh-bridge-ros2dds): /scan /odom /drive_out out, /drive in (extra: ros2)"),
    "record": ("racecav.services.record.record", "record the car's keys to one MCAP file: raw samples + ROS 2 /scan /odom /drive (extra: record)"),
    "replay": ("racecav.services.record.replay", "replay a recorded run's scans into a running controller and compare its commands with the recorded ones"),
    "viz": ("racecav.services.viz.service", "live Foxglove view (WebSocket): scan, car and obstacle boxes, walls, commands, latency; --mcap PATH (extra: viz)"),
}

class Parser(argparse.ArgumentParser):
    """argparse with a one-line error (the option and the rule, then where help is), exit 2.
    Subcommand parsers inherit it (argparse makes them of the parent's class)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="racecav", description=__doc__.splitlines()[0])
    parser.add_argument("--config", help="TOML config file (default: $RACECAV_CONFIG or built-in defaults)")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        # --config after the subcommand too (`racecav sim --config car.toml`), as users type it.
        p.add_argument("--config", default=argparse.SUPPRESS, help="TOML config file")
        p.set_defaults(_module=module)
        add_arguments_of(module, p)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import logging

    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        cfg = load_config(args.config)
    except ConfigError as e:
        print(f"racecav: {e}", file=sys.stderr)
        return 2
    from racecav.common import procs

    procs.install_cleanup()  # every process this command starts is stopped when it ends, however
    try:
        return int(importlib.import_module(args._module).run(args, cfg) or 0)
    except ConfigError as e:  # a bad set-up found while starting (bus, files, ports): one line
        print(f"racecav {args.command}: {e}", file=sys.stderr)
        return 2
    except (FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError) as e:
        if not e.filename:
            raise
        # a path the command was given that cannot be used: a bad set-up, one line
        print(f"racecav {args.command}: {e.filename}: {e.strerror}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
