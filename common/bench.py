"""``racecav bench NAME``: benchmark runner and the writer of docs/benchmarks.md.

Every benchmark reports medians and p99 and rewrites its own section of docs/benchmarks.md
(between ``<!-- bench:NAME -->`` markers), with the command that produced it, so the document only
ever holds numbers a command measured.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import re
from pathlib import Path

import numpy as np

from racecav.common.subcommands import add_table, run_table

DOC = Path("docs/benchmarks.md")
HEADER = """# Benchmarks

Every section below is written by the command it names, on the machine it names; nothing here is
typed by hand. Run-to-run noise on the 2-core reference machine is about +-20 %: compare ratios
measured in one run. Regenerate a section with its command (from the repository root).
"""


# `racecav bench NAME`: name -> (module, help); the module exposes add_arguments/run too.
BENCHES: dict[str, tuple[str, str]] = {
    "lidar": ("racecav.services.sensor.bench", "RPLIDAR dense decoding and preprocessing cost, live driver CPU over a pty"),
    "vesc": ("racecav.services.actuator.bench", "DriveCommand-to-VESC latency and watchdog reaction, timed at the emulator"),
    "env": ("racecav.training.bench_env", "env-steps/s of the fast training world (1 and 2 processes) vs PyBullet"),
    "bus": ("racecav.common.bench_bus", "scan publish-to-receive latency (client and peer mode), status queries, codec"),
    "train": ("racecav.training.bench_train", "PPO samples/s: the paper's setting vs more envs per rollout, larger minibatches, fewer epochs"),
    "sim": ("racecav.services.sim.bench", "PyBullet 16-car racetrack steps/s (lidar on agent / all cars) and the sim service's real-time factor"),
    "faults": ("racecav.services.bench_faults", "reliability: kill -> brake, e-stop latch, lidar replug, router restart, fuzz; writes docs/reliability.md"),
    "controllers": ("racecav.services.bench_controllers", "paper Table 2 on this machine: FLOPs, in-process and end-to-end latency of policy and MPC-APF"),
    "record": ("racecav.services.record.bench", "policy scan->command latency with racecav record / racecav ros2 running beside it; their per-message cost"),
    "ray": ("racecav.evaluation.bench_ray", "eval --table --ray against the local pool (--jobs) on this machine; the full table's wall time on N machines, projected (extra: ray)"),
    "safety": ("racecav.services.safety.bench", "safety supervisor: scan -> brake latency (real processes), false brakes over ~100 laps of the empty tracks (shadow mode)"),
}


def summarize(samples, scale: float = 1.0) -> dict:
    """Median, p99, mean, min, max and count of ``samples`` multiplied by ``scale``."""
    a = np.asarray(samples, dtype=float) * scale
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "median": float(np.median(a)), "p99": float(np.percentile(a, 99)),
            "mean": float(a.mean()), "min": float(a.min()), "max": float(a.max())}


def git_commit() -> str:
    """The checkout's commit (``git describe --always --dirty``): provenance of every result."""
    import subprocess

    try:
        return subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=12"], capture_output=True,
                              text=True, timeout=5, cwd=Path(__file__).resolve().parents[1]).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def machine() -> str:
    return f"{platform.node() or 'host'}: {os.cpu_count()} cores, {platform.machine()}, Python {platform.python_version()}"


def write_section(name: str, command: str, markdown: str, doc: Path = DOC) -> Path:
    """Replace (or append) the section ``name`` of docs/benchmarks.md."""
    doc.parent.mkdir(parents=True, exist_ok=True)
    text = doc.read_text() if doc.exists() else HEADER
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    body = (f"<!-- bench:{name} -->\n## {name}\n\nCommand: `{command}`  \n"
            f"Measured {stamp} on {machine()}.\n\n{markdown.strip()}\n<!-- /bench:{name} -->")
    pattern = re.compile(rf"<!-- bench:{re.escape(name)} -->.*?<!-- /bench:{re.escape(name)} -->", re.S)
    text = pattern.sub(lambda _m: body, text) if pattern.search(text) else text.rstrip() + "\n\n" + body + "\n"
    doc.write_text(text)
    return doc


def table(rows: list[list], header: list[str]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def dump_json(path: str | None, data: dict) -> None:
    if path:
        Path(path).write_text(json.dumps(data, indent=2))


def _common_options(q: argparse.ArgumentParser) -> None:
    q.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    q.add_argument("--no-doc", action="store_true", help="do not rewrite docs/benchmarks.md")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_table(p, "bench", BENCHES, extra=_common_options)


def run(args: argparse.Namespace, cfg) -> int:
    return run_table(args, cfg, "bench", BENCHES)
