"""``racecav demo``: the README's main command (``make demo``).

Starts the car's router, the sim service on the head-to-head scenario and the shipped avoid
policy service (trained on conflicts, common/data/policies/avoid.*) as separate processes (the evaluation harness does it, exactly
as ``racecav eval`` does), runs a few seeded trials through them over Zenoh, prints each trial's
outcome and the scan-to-command latency, writes the trajectory plot, and stops everything.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from racecav.common.config import Config


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=int, default=5, help="trials to run")
    p.add_argument("--scenario", default="head-to-head", help="scenario name or TOML file")
    p.add_argument("--controller", default="drl-avoid", help="controller (see racecav eval --help; default: the "
                   "shipped avoid policy, trained on conflicts)")
    p.add_argument("--mode", choices=["lockstep", "realtime"], default="lockstep",
                   help="lockstep: reproducible, as fast as the machine allows; realtime: wall clock like the car")
    p.add_argument("--out-dir", type=Path, default=Path("runs/demo"), help="results, plot and logs")


def run(args: argparse.Namespace, cfg: Config) -> int:
    from racecav.evaluation.trials import run_single
    from racecav.evaluation.harness import CONTROLLERS, missing

    ctrl = CONTROLLERS.get(args.controller)
    if ctrl is None:
        print(f"racecav demo: unknown controller {args.controller!r}; known: {sorted(CONTROLLERS)}", file=sys.stderr)
        return 2
    why = missing(ctrl)
    if why:
        print(f"racecav demo: cannot run the demo: {why}.\n"
              f"The demo drives the sim with the shipped {ctrl.label} policy; it is produced by "
              "`racecav train` (see docs/training.md) and committed to the repository. "
              "Nothing was started.", file=sys.stderr)
        return 1
    try:  # a folder that cannot be made is a bad set-up: one line, exit 2
        Path(args.out_dir).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        print(f"racecav demo: --out-dir {args.out_dir}: cannot create the folder ({e.strerror or e})", file=sys.stderr)
        return 2
    if getattr(args, "config", None):  # the services started below read the same file
        import os

        os.environ["RACECAV_CONFIG"] = str(Path(args.config).resolve())
    print(f"racecav demo: router + `racecav sim --scenario {args.scenario} --mode {args.mode}` + "
          f"`racecav {' '.join(ctrl.args)}` as separate processes; {args.trials} trials over Zenoh")
    eval_args = argparse.Namespace(
        scenario=args.scenario, controller=args.controller, trials=args.trials, seed=None, mode=args.mode,
        real_time_factor=1.0, json=None, jsonl=None, plot=None, plot_trials=min(args.trials, 3), resume=False,
        out_dir=args.out_dir, no_progress=False, model=None)
    rc = run_single(eval_args, cfg, per_trial=True)
    if rc == 0:
        print("racecav demo: done; all processes stopped")
    return rc
