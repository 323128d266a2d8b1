"""Running evaluation trials on a harness: one scenario's seeded trials (resumable JSONL), the
results JSON, summaries and plots; ``run_single`` is ``racecav eval --scenario S --controller C``.
The command line itself is :mod:`racecav.evaluation.evaluate`; the table and the suite run their
cells through :func:`run_trials` too.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import signal
import sys
import time
from pathlib import Path

from racecav.common.bench import git_commit
from racecav.common.config import Config


class Interrupted(Exception):
    """SIGINT/SIGTERM during an evaluation."""


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


def cell_key(ctrl, safety: bool, mode: str, path: Path, base_seed: int) -> str:
    """The run key of a controller's trials on a scenario file (results.run_key): what makes two
    runs' trials interchangeable. With the safety supervisor the controller is CONTROLLER+safety."""
    from racecav.evaluation import results as R

    weights = R.file_digest(ctrl.model) if ctrl.model is not None else None
    return R.run_key(R.file_digest(path), ctrl.name + ("+safety" if safety else ""), mode, base_seed, weights)


def run_trials(harness, ref: str, path: Path, trials: int, base_seed: int, jsonl: Path, resume: bool,
               bar=None, keep_trajectory: bool = True, store=None):
    """Run (or resume) ``trials`` trials of one scenario on an open harness.

    :param path: the scenario file (its digest keys the run). :param bar: a shared progress bar.
    :param store: (CellStore, row, group, cell): with ``resume`` a complete stored cell of the same
        run key is returned without running a trial; a cell that completes here is stored.
    :returns: (RunResult, the exception that stopped it or None). The result is partial
        (``complete: false``, ``stopped_reason``) when not every trial finished.
    """
    from racecav.common.bench import machine
    from racecav.common.scenario import load_scenario
    from racecav.evaluation import results as R

    sc = load_scenario(ref)
    digest = R.file_digest(path)
    weights = R.file_digest(harness.ctrl.model) if harness.ctrl.model is not None else None
    safety = getattr(harness, "safety", False)
    name = harness.ctrl.name + ("+safety" if safety else "")
    key = cell_key(harness.ctrl, safety, harness.mode, path, base_seed)
    if store is not None and resume:
        hit = store[0].get(*store[1:], key, trials)
        if hit is not None:
            if bar is not None:
                bar.update(trials)
            return hit, None
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
        if info.get("lockstep_compute_ms") is not None:  # a fixed charge (SimConfig.lockstep_compute_ms)
            sim_counters["lockstep_compute_ms"] = info["lockstep_compute_ms"]
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
                                    service=harness.ctrl.service, weights_sha256=weights,
                                    compute_charge_ms=getattr(harness, "charge_ms", None)),
        mode=harness.mode, base_seed=base_seed, trials_requested=trials, complete=len(finished) == trials,
        stopped_reason=stopped, wall_s=time.monotonic() - wall0, summary=R.summarize(finished),
        sim_counters=sim_counters, controller_counters=ctrl_counters, trials=finished)
    if store is not None:
        store[0].put(*store[1:], res)
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
    from racecav.evaluation.plots import plot_trajectories

    shown = [t for t in res.trials if t.trajectory is not None][:n]
    if not shown:
        return None
    walls = load_scenario(res.scenario.ref).build_world().walls
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


def trial_line(t) -> str:
    from racecav.evaluation.plots import outcome

    gap = "n/a" if t.min_gap_m is None else f"{t.min_gap_m:.2f} m"
    lat = "n/a" if t.latency_ms.median is None else f"{t.latency_ms.median:.2f} ms (p99 {t.latency_ms.p99:.2f})"
    return (f"  trial {t.index} (seed {t.seed}): {outcome(t)}; min gap {gap}, progress {t.progress_m:.1f} m, "
            f"scan->command {lat}")


def _raise_interrupted(signum, _frame):
    raise Interrupted(signal.Signals(signum).name)


def guarded(fn) -> int:
    """SIGTERM behaves like Ctrl-C: partial results are written, processes stopped."""
    old = signal.signal(signal.SIGTERM, _raise_interrupted)
    try:
        return fn()
    finally:
        signal.signal(signal.SIGTERM, old)


def eval_perturb(args: argparse.Namespace, cfg: Config):
    """The sim's perturbation of an evaluation: ``--perturb`` (one line naming an unknown preset
    or key: ValueError), else the configuration's sim.perturb; timing needs lockstep."""
    from racecav.common.config import PerturbConfig
    from racecav.common.perturb import parse_text

    text = getattr(args, "perturb", None)
    try:
        p = cfg.sim.perturb if text is None else PerturbConfig.model_validate(parse_text(text))
    except ValueError as e:
        msg = str(e) if not hasattr(e, "errors") else "; ".join(
            f"{'.'.join(map(str, x['loc']))}: {x['msg']}" for x in e.errors())
        raise ValueError(f"--perturb: {msg.removeprefix('perturb: ')}") from None
    if p.timing() and getattr(args, "mode", "lockstep") != "lockstep":
        raise ValueError("--perturb: scan_jitter_s, latency_s and actuator_delay_s need --mode lockstep")
    return p


def with_model(ctrl, model: Path | None):
    """``ctrl`` running the policy file ``model`` (``--model``) instead of its shipped weights
    (``ctrl`` itself when ``model`` is None).

    :raises ValueError: ``ctrl`` is not a drl-* controller.
    """
    if model is None:
        return ctrl
    if ctrl.service != "policy":
        raise ValueError(f"--model applies to the drl-* controllers, not {ctrl.name}")
    model = Path(model).resolve()
    return dataclasses.replace(ctrl, args=("policy", "--model", str(model)), model=model)


def run_single(args: argparse.Namespace, cfg: Config, per_trial: bool = False) -> int:
    """One scenario x one controller (``racecav eval --scenario S --controller C``).

    :param per_trial: also print one line per trial (the demo).
    """
    from racecav.common.scenario import load_scenario
    from racecav.evaluation.harness import CONTROLLERS, Harness, HarnessError, missing, perturbed

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
    try:
        perturb = eval_perturb(args, cfg)
    except ValueError as e:
        print(f"racecav eval: {e}", file=sys.stderr)
        return 2
    try:
        ctrl = with_model(ctrl, getattr(args, "model", None))
    except ValueError as e:
        print(f"racecav eval: {e}", file=sys.stderr)
        return 2
    why = missing(ctrl)
    if why:
        print(f"racecav eval: cannot evaluate {ctrl.name}: {why}", file=sys.stderr)
        return 2
    ctrl = perturbed(ctrl, perturb)
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
                     record_dir=record_dir, safety=safety,
                     compute_charge=getattr(args, "compute_charge", "fixed"), perturb=perturb) as h:
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
