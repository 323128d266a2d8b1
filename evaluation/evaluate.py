"""``racecav eval``: success rates, distances and latency of a controller, through the real services.

One run: ``racecav eval --scenario NAME|FILE --controller C [--trials N] [--seed S] [--mode M]``
starts a router, ``racecav sim`` and the controller's service as separate processes
(:mod:`racecav.evaluation.harness`), runs N seeded trials, and writes the results JSON (schema:
docs/results-schema.json), a JSONL of per-trial records written as each trial ends, and a
trajectory plot like the paper's Figure 4.

The table: ``racecav eval --table [--trials N]`` runs every controller on the three intersection
scenarios and writes docs/results.md beside the paper's Table 1 (:mod:`racecav.evaluation.table`).

Interruptions: every finished trial is already in the JSONL; ``--resume`` continues from it
(same controller, mode, seed and scenario file, or it refuses). An interrupted or failed run
still writes its JSON, marked ``complete: false`` with the reason, and exits non-zero: a run is
never silently short.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from racecav.common import registry
from racecav.common.config import Config
from racecav.evaluation import ray_cells
from racecav.evaluation.trials import guarded, run_single

OUT_DIR = Path("runs/eval")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", help="scenario name (right-to-left, head-to-head, left-to-right, ...) "
                   "or a scenario TOML file (schema: docs/world.md)")
    p.add_argument("--controller", choices=list(registry.CONTROLLERS),
                   help="drl-avoid | drl-reversed | drl-default | drl-racing (racecav policy --model ...), mpc-apf "
                   "(racecav baseline), mpc-apf-fast (the baseline at v_ref 2.7 m/s), scripted / full-throttle "
                   "(straight ahead at 1 m/s / full throttle, no evasion: references)")
    p.add_argument("--model", type=Path, help="drl-* controllers: evaluate this policy .npz instead of the "
                   "shipped weights (e.g. a checkpoint before shipping)")
    p.add_argument("--suite", help="a conflict suite (NAME under runs/suites or DIR with suite.json, from "
                   "`racecav suite generate`): every file of --split, per-family success (with --table: the "
                   "suite section's suite, default conflicts)")
    p.add_argument("--split", default="test", choices=["test", "train", "ood", "controls"],
                   help="--suite: which split (default test; ood and controls: a roads suite)")
    p.add_argument("--trials-per-scenario", type=int, default=5,
                   help="--suite: trials per scenario file (default 5: 100 per family of 20 files)")
    p.add_argument("--table", action="store_true",
                   help="every controller x the three intersection scenarios; writes docs/results.md")
    p.add_argument("--sections", help="--table: comma-separated subset of table1,conflict,suite,free,roads "
                   "(default all: the paper's Table 1, the conflict-timed paper scenarios, the conflict suite's test "
                   "split per family, the open suite's test split: free intersections, the roads suite's test / "
                   "ood / controls splits: generalization)")
    p.add_argument("--roads-controllers", help="--table: the rows of the generalization section (roads), a "
                   "comma-separated subset of --controllers (default: all of them; none: no row)")
    p.add_argument("--roads-suite", help="--table: the generalization section's suite (default roads, under "
                   "runs/suites, generated first when missing; or a DIR with suite.json); the section is skipped, with "
                   "a message, when there is no such suite")
    p.add_argument("--controllers", help="--table: comma-separated subset "
                   "(default: mpc-apf,drl-default,drl-reversed,scripted,full-throttle,mpc-apf-fast)")
    p.add_argument("--trials", type=int, help="trials per scenario (default 10; --table: 100)")
    p.add_argument("--seed", type=int, help="seed of trial 0 (trial i: seed + i); default: the scenario's seed")
    p.add_argument("--mode", choices=["lockstep", "realtime"], default="lockstep",
                   help="sim mode: lockstep (reproducible; the controller's compute time is charged "
                   "as actuation delay) or realtime (wall clock)")
    p.add_argument("--compute-charge", choices=["fixed", "measured"], default="fixed",
                   help="lockstep: the compute time charged to each command: fixed (default: the controller's "
                   "benchmarked time, the registry's charge_ms, so a cell repeats whatever the machine's load) or "
                   "measured (each command's own compute_ns: moves with the load)")
    p.add_argument("--real-time-factor", type=float, default=1.0, help="realtime mode: sim s per wall s")
    p.add_argument("--json", type=Path, help="results file (default runs/eval/SCENARIO-CONTROLLER.json)")
    p.add_argument("--jsonl", type=Path, help="per-trial progress file (default: the --json path with .jsonl)")
    p.add_argument("--plot", type=Path, help="trajectory plot PNG (default: the --json path with .png)")
    p.add_argument("--plot-trials", type=int, default=3, help="trials shown in the trajectory plot")
    p.add_argument("--resume", action="store_true", help="continue from the trials already in the JSONL "
                   "(--table: and from the committed cells of --store)")
    p.add_argument("--out-dir", type=Path, default=OUT_DIR, help="where runs, logs and JSONL files go")
    p.add_argument("--doc", type=Path, default=Path("docs/results.md"), help="--table: the document written")
    p.add_argument("--store", type=Path, help="--table: the committed store of complete cells that --resume "
                   "reuses and every complete cell is written to (default: results-data/ beside --doc; "
                   "evaluation/store.py)")
    p.add_argument("--from-store", action="store_true",
                   help="--table: write the document from the --store cells alone (implies --resume): no "
                        "service starts, and a cell the store lacks is an error (exit 2) naming its row")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--jobs", type=int, default=1,
                   help="--table: run the (controller, safety) rows in a pool of N processes (each about "
                        "one core: its own router, sim and controller), the rows with most trials left first, "
                        "then write the document from their cells")
    p.add_argument("--ray", nargs="?", const="", metavar="ADDRESS",
                   help="--table/--suite: run each cell as a Ray task (extra: ray; docs/cluster.md) on the "
                        "cluster at ADDRESS (host:port of `ray start --head`, or auto), or on a local Ray "
                        "started on this machine's cores when no ADDRESS is given")
    p.add_argument("--ray-cpus", type=float, default=ray_cells.CELL_CPUS,
                   help="--ray: CPUs each cell requests (its sim and controller keep about two cores busy)")
    p.add_argument("--ray-retries", type=int, default=ray_cells.RETRIES,
                   help="--ray: times a cell whose worker or node died is run again")
    p.add_argument("--safety", choices=["on", "off", "both"], default="off",
                   help="on: also run racecav safety (the emergency-brake supervisor, a brake input of the "
                        "sim's mux); results go to *-safety.json, the controller is named CONTROLLER+safety; "
                        "both (--table only): every cell without and with it, and the on/off table")
    p.add_argument("--perturb", metavar="PRESET|KEY=VALUE,...",
                   help="run the sim under sim-to-real perturbations (a preset of common/data/perturbations.toml, "
                        "key=value pairs of sim.perturb, or both; docs/robustness.md); results are named "
                        "CONTROLLER@PERTURBATION")
    p.add_argument("--robust-trials", type=int, default=30,
                   help="--table --sections robust: trials per scenario cell under each perturbation (default 30)")
    p.add_argument("--robust-suite-trials", type=int, default=1,
                   help="--table --sections robust: trials per file of the conflict suite's test split under "
                        "each preset and the ideal world (default 1; 0: no suite part)")
    p.add_argument("--robust-controllers", default="drl-avoid,drl-reversed,mpc-apf",
                   help="--table --sections robust: the controllers (default drl-avoid,drl-reversed,mpc-apf)")
    p.add_argument("--record", nargs="?", const=True, type=Path, metavar="DIR",
                   help="write one MCAP run file per trial (racecav record; default DIR: "
                        "OUT_DIR/mcap/SCENARIO-CONTROLLER); replay one with racecav replay")


def run(args: argparse.Namespace, cfg: Config) -> int:
    if getattr(args, "config", None):  # the services the harness starts read the same file
        os.environ["RACECAV_CONFIG"] = str(Path(args.config).resolve())
    if getattr(args, "out_dir", None) is not None:  # a folder that cannot be made: one line, exit 2
        try:
            Path(args.out_dir).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            print(f"racecav eval: --out-dir {args.out_dir}: cannot create the folder ({e.strerror or e})",
                  file=sys.stderr)
            return 2
    if args.ray is not None and not (args.table or (args.suite and args.controller)):
        print("racecav eval: --ray is for --table and --suite (a single scenario runs here)", file=sys.stderr)
        return 2
    if args.ray is not None and getattr(args, "model", None) is not None:
        # a Ray worker builds its controller from the registry by name: it would run the shipped weights
        print("racecav eval: --model runs locally, not with --ray (a Ray worker builds its controller by name, "
              "with the shipped weights)", file=sys.stderr)
        return 2
    if args.ray is not None and (args.ray_cpus <= 0 or args.ray_retries < 0):
        print("racecav eval: --ray-cpus must be > 0 and --ray-retries >= 0", file=sys.stderr)
        return 2
    if args.table:
        if getattr(args, "model", None) is not None:
            print("racecav eval: --model is for single runs (--scenario/--controller), not --table", file=sys.stderr)
            return 2
        from racecav.evaluation.table import run_table

        return guarded(lambda: run_table(args, cfg))
    if args.safety == "both":
        print("racecav eval: --safety both is for --table (a single run is on or off)", file=sys.stderr)
        return 2
    if args.suite and args.controller:
        from racecav.evaluation.suite_eval import run_suite

        return guarded(lambda: run_suite(args, cfg))
    if not args.scenario or not args.controller:
        print("racecav eval: --scenario (or --suite) and --controller are required (or --table)", file=sys.stderr)
        return 2
    return guarded(lambda: run_single(args, cfg))


