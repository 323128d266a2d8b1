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
import dataclasses
import datetime as dt
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from racecav.common import registry
from racecav.common.bench import git_commit
from racecav.common.config import Config

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
    p.add_argument("--split", default="test", choices=["test", "train"], help="--suite: which split (default test)")
    p.add_argument("--trials-per-scenario", type=int, default=5,
                   help="--suite: trials per scenario file (default 5: 100 per family of 20 files)")
    p.add_argument("--table", action="store_true",
                   help="every controller x the three intersection scenarios; writes docs/results.md")
    p.add_argument("--sections", help="--table: comma-separated subset of table1,conflict,suite (default all: "
                   "the paper's Table 1, the conflict-timed paper scenarios, the suite's test split per family)")
    p.add_argument("--controllers", help="--table: comma-separated subset "
                   "(default: mpc-apf,drl-default,drl-reversed,scripted,full-throttle,mpc-apf-fast)")
    p.add_argument("--trials", type=int, help="trials per scenario (default 10; --table: 100)")
    p.add_argument("--seed", type=int, help="seed of trial 0 (trial i: seed + i); default: the scenario's seed")
    p.add_argument("--mode", choices=["lockstep", "realtime"], default="lockstep",
                   help="sim mode: lockstep (reproducible; the controller's compute time is charged "
                   "as actuation delay) or realtime (wall clock)")
    p.add_argument("--real-time-factor", type=float, default=1.0, help="realtime mode: sim s per wall s")
    p.add_argument("--json", type=Path, help="results file (default runs/eval/SCENARIO-CONTROLLER.json)")
    p.add_argument("--jsonl", type=Path, help="per-trial progress file (default: the --json path with .jsonl)")
    p.add_argument("--plot", type=Path, help="trajectory plot PNG (default: the --json path with .png)")
    p.add_argument("--plot-trials", type=int, default=3, help="trials shown in the trajectory plot")
    p.add_argument("--resume", action="store_true", help="continue from the trials already in the JSONL")
    p.add_argument("--out-dir", type=Path, default=OUT_DIR, help="where runs, logs and JSONL files go")
    p.add_argument("--doc", type=Path, default=Path("docs/results.md"), help="--table: the document written")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--safety", choices=["on", "off"], default="off",
                   help="on: also run racecav safety (the emergency-brake supervisor, a brake input of the "
                        "sim's mux); results go to *-safety.json, the controller is named CONTROLLER+safety")
    p.add_argument("--record", nargs="?", const=True, type=Path, metavar="DIR",
                   help="write one MCAP run file per trial (racecav record; default DIR: "
                        "OUT_DIR/mcap/SCENARIO-CONTROLLER); replay one with racecav replay")


class Interrupted(Exception):
    """SIGINT/SIGTERM during an evaluation."""


def _raise_interrupted(signum, _frame):
    raise Interrupted(signal.Signals(signum).name)


def scenario_ref(name_or_path: str) -> tuple[str, Path]:
    """The reference the sim process should load (absolute for files) and the file itself.

    :raises ValueError: from :func:`load_scenario`, naming the file and the invalid field.
    """
    from racecav.common.scenario import SCENARIOS_DIR, load_scenario

    p = Path(name_or_path)
    load_scenario(name_or_path)  # refuse a broken file here, before any process starts
    if p.suffix:
        return str(p.resolve()), p.resolve()
    return name_or_path, SCENARIOS_DIR / f"{name_or_path}.toml"


def run_trials(harness, ref: str, path: Path, trials: int, base_seed: int, jsonl: Path, resume: bool,
               bar=None, keep_trajectory: bool = True):
    """Run (or resume) ``trials`` trials of one scenario on an open harness.

    :param path: the scenario file (its digest keys the run). :param bar: a shared progress bar.
    :returns: (RunResult, the exception that stopped it or None). The result is partial
        (``complete: false``, ``stopped_reason``) when not every trial finished.
    """
    from racecav.common.bench import machine
    from racecav.common.scenario import load_scenario
    from racecav.evaluation import results as R

    sc = load_scenario(ref)
    digest = R.file_digest(path)
    weights = R.file_digest(harness.ctrl.model) if harness.ctrl.model is not None else None
    # with the safety supervisor the controller under test is CONTROLLER+safety
    name = harness.ctrl.name + ("+safety" if getattr(harness, "safety", False) else "")
    key = R.run_key(digest, name, harness.mode, base_seed, weights)
    jsonl.parent.mkdir(parents=True, exist_ok=True)
    done = R.read_jsonl(jsonl, key) if resume else {}
    if not resume and jsonl.exists():
        jsonl.unlink()
    todo = [i for i in range(trials) if i not in done]
    own_bar = bar is None
    if own_bar:
        from tqdm import tqdm

        bar = tqdm(total=trials, desc=f"{harness.ctrl.name} {sc.name}", unit="trial", dynamic_ncols=True,
                   mininterval=1.0)
    bar.update(trials - len(todo))
    wall0 = time.monotonic()
    stopped, error = "", None
    harness.set_scenario(ref)
    try:
        for i in todo:
            trial = harness.run_trial(i, base_seed + i, keep_trajectory)
            done[i] = trial
            R.append_jsonl(jsonl, key, trial)
            ok = sum(t.success for t in done.values())
            bar.set_postfix_str(f"{sc.name} success {ok}/{len(done)}")
            bar.update(1)
    except Interrupted as e:
        stopped, error = f"interrupted ({e})", e
    except KeyboardInterrupt as e:
        stopped, error = "interrupted (SIGINT)", e
    except Exception as e:  # a harness error: report partial results, not a traceback alone
        stopped, error = f"error: {e}", e
    finally:
        if own_bar:
            bar.close()
    finished = [done[i] for i in sorted(done) if i < trials]
    sim_counters, ctrl_counters = {}, {}
    try:
        info = harness.status_info()
        sim_counters = {k: info[k] for k in ("lockstep_republish", "stale_commands", "watchdog_brakes", "overruns",
                                             "episode", "safety_brakes", "safety_verdict_timeouts") if k in info}
        ctrl_counters = harness.controller_status().info
        if getattr(harness, "safety", False):  # the supervisor's brakes and false-brake candidates
            from racecav.common.client import get_status

            ctrl_counters["safety"] = get_status(harness.session, harness.car_name, "safety", timeout=5.0).info
    except Exception as e:  # a dead process: the stopped_reason already says why
        sim_counters = {"status_error": str(e)[:200]}
    res = R.RunResult(
        created_utc=dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"), git_commit=git_commit(),
        machine=machine(),
        scenario=R.ScenarioInfo(name=sc.name, ref=ref, digest=digest, duration_s=sc.duration_s),
        controller=R.ControllerInfo(name=name, command=["racecav", *harness.ctrl.args],
                                    service=harness.ctrl.service, weights_sha256=weights),
        mode=harness.mode, base_seed=base_seed, trials_requested=trials, complete=len(finished) == trials,
        stopped_reason=stopped, wall_s=time.monotonic() - wall0, summary=R.summarize(finished),
        sim_counters=sim_counters, controller_counters=ctrl_counters, trials=finished)
    return res, error


def write_json(res, path: Path) -> Path:
    from racecav.evaluation.results import validate_run

    path.parent.mkdir(parents=True, exist_ok=True)
    text = res.model_dump_json(indent=1)
    validate_run(json.loads(text))  # what we write is what the schema promises
    path.write_text(text + "\n")
    return path


def plot_run(res, path: Path, n: int = 3) -> Path | None:
    from racecav.common.scenario import load_scenario
    from racecav.common.vehicle import load_car
    from racecav.common.world import load_world
    from racecav.evaluation.plots import plot_trajectories

    shown = [t for t in res.trials if t.trajectory is not None][:n]
    if not shown:
        return None
    walls = load_world(load_scenario(res.scenario.ref).world).walls
    car = load_car()
    return plot_trajectories([(t, f"trial {t.index}") for t in shown], [walls] * len(shown), path,
                             title=f"{res.controller.name} on {res.scenario.name} ({res.mode})",
                             car_size=(car.length, car.width))


def summary_line(res) -> str:
    s = res.summary
    if not s.trials:
        return f"{res.controller.name} on {res.scenario.name}: no trial finished"
    lo, hi = s.ci95
    lat, comp = s.latency_ms, s.compute_ms
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
    return (f"{res.controller.name} on {res.scenario.name}: success {s.successes}/{s.trials} = "
            f"{100 * s.success_rate:.0f} % (95 % CI {100 * lo:.0f}-{100 * hi:.0f} %), collisions {s.collisions}, "
            f"mean progress {s.mean_progress_m:.2f} m, median min gap "
            f"{'n/a' if s.median_min_gap_m is None else f'{s.median_min_gap_m:.2f} m'}\n"
            f"  scan->command latency median {fmt(lat.median)} ms, p99 {fmt(lat.p99)} ms (n={lat.n}); "
            f"controller compute median {fmt(comp.median)} ms, p99 {fmt(comp.p99)} ms")


def run(args: argparse.Namespace, cfg: Config) -> int:
    if getattr(args, "config", None):  # the services the harness starts read the same file
        os.environ["RACECAV_CONFIG"] = str(Path(args.config).resolve())
    if args.table:
        if getattr(args, "model", None) is not None:
            print("racecav eval: --model is for single runs (--scenario/--controller), not --table", file=sys.stderr)
            return 2
        from racecav.evaluation.table import run_table

        return _guarded(lambda: run_table(args, cfg))
    if args.suite and args.controller:
        from racecav.evaluation.suite_eval import run_suite

        return _guarded(lambda: run_suite(args, cfg))
    if not args.scenario or not args.controller:
        print("racecav eval: --scenario (or --suite) and --controller are required (or --table)", file=sys.stderr)
        return 2
    return _guarded(lambda: run_single(args, cfg))


def _guarded(fn) -> int:
    """SIGTERM behaves like Ctrl-C: partial results are written, processes stopped."""
    old = signal.signal(signal.SIGTERM, _raise_interrupted)
    try:
        return fn()
    finally:
        signal.signal(signal.SIGTERM, old)


def trial_line(t) -> str:
    from racecav.evaluation.plots import outcome

    gap = "n/a" if t.min_gap_m is None else f"{t.min_gap_m:.2f} m"
    lat = "n/a" if t.latency_ms.median is None else f"{t.latency_ms.median:.2f} ms (p99 {t.latency_ms.p99:.2f})"
    return (f"  trial {t.index} (seed {t.seed}): {outcome(t)}; min gap {gap}, progress {t.progress_m:.1f} m, "
            f"scan->command {lat}")


def run_single(args: argparse.Namespace, cfg: Config, per_trial: bool = False) -> int:
    """One scenario x one controller (``racecav eval --scenario S --controller C``).

    :param per_trial: also print one line per trial (the demo).
    """
    from racecav.common.scenario import load_scenario
    from racecav.evaluation.harness import CONTROLLERS, Harness, HarnessError, missing

    trials = args.trials if args.trials is not None else 10
    if trials < 1:
        print("racecav eval: --trials must be >= 1", file=sys.stderr)
        return 2
    try:
        ref, path = scenario_ref(args.scenario)
    except ValueError as e:
        print(f"racecav eval: {e}", file=sys.stderr)
        return 2
    ctrl = CONTROLLERS[args.controller]
    if getattr(args, "model", None) is not None:
        if ctrl.service != "policy":
            print(f"racecav eval: --model applies to the drl-* controllers, not {ctrl.name}", file=sys.stderr)
            return 2
        model = args.model.resolve()
        ctrl = dataclasses.replace(ctrl, args=("policy", "--model", str(model)), model=model)
    why = missing(ctrl)
    if why:
        print(f"racecav eval: cannot evaluate {ctrl.name}: {why}", file=sys.stderr)
        return 2
    sc = load_scenario(ref)
    seed = args.seed if args.seed is not None else sc.seed
    safety = getattr(args, "safety", "off") == "on"
    stem = (f"{sc.name}-{ctrl.name}" + ("" if args.mode == "lockstep" else f"-{args.mode}")
            + ("-safety" if safety else ""))
    json_path = args.json or args.out_dir / f"{stem}.json"
    jsonl = args.jsonl or json_path.with_suffix(".jsonl")
    plot = args.plot or json_path.with_suffix(".png")
    error = None
    try:
        record = getattr(args, "record", None)
        record_dir = (args.out_dir / "mcap" / stem) if record is True else record
        with Harness(cfg, ctrl, args.mode, ref, args.out_dir / "logs" / stem, args.real_time_factor,
                     record_dir=record_dir, safety=safety) as h:
            res, error = run_trials(h, ref, path, trials, seed, jsonl, args.resume,
                                    bar=NoBar() if args.no_progress else None)
    except HarnessError as e:
        print(f"racecav eval: {e}", file=sys.stderr)
        return 1
    except (Interrupted, KeyboardInterrupt):
        print("racecav eval: interrupted while starting the services; nothing measured", file=sys.stderr)
        return 130
    except ValueError as e:  # a JSONL of another run
        print(f"racecav eval: {e}", file=sys.stderr)
        return 2
    write_json(res, json_path)
    if per_trial:
        for t in res.trials:
            print(trial_line(t))
    print(summary_line(res))
    if res.trials:
        print(f"trajectories: {plot_run(res, plot, args.plot_trials)}")
    print(f"results: {json_path} (per trial: {jsonl})")
    if not res.complete:
        print(f"PARTIAL: {len(res.trials)} of {trials} trials ({res.stopped_reason}); "
              f"continue with the same command and --resume", file=sys.stderr)
        return 130 if isinstance(error, (Interrupted, KeyboardInterrupt)) else 1
    return 0


class NoBar:
    """Stand-in for tqdm with --no-progress."""

    def __init__(self, *_a, **_k):
        pass

    def update(self, *_):
        pass

    def set_postfix_str(self, *_):
        pass

    def set_description_str(self, *_):
        pass

    def close(self):
        pass

