"""``racecav eval --suite NAME|DIR``: a controller over a conflict suite's split, per family.

Every scenario file of the split (default: test) runs ``--trials-per-scenario`` seeded trials
(trial i: seed + i) through the real services, one harness for the whole split (the sim switches
scenario files through its queryable). Results: success per family and overall with 95 % Wilson
intervals, collisions, min gap, progress; one JSON (``summary`` as in a single run, plus
``families``) and a per-family bar chart. Each file keeps its per-trial JSONL under
runs/eval/suite-NAME-SPLIT/CONTROLLER/, so ``--resume`` continues an interrupted run.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Cell:
    """One scenario file of a suite, with its family."""

    path: Path
    family: str


def suite_cells(spec: str, split: str) -> tuple[str, list[Cell]]:
    """(suite name, cells of the split) of a generated suite.

    :raises ValueError: when there is no such suite or split.
    """
    from racecav.common.scenario import open_suite

    s = open_suite(spec)
    if split not in s.manifest["splits"]:
        raise ValueError(f"suite {spec}: no split {split!r} (have {sorted(s.manifest['splits'])})")
    return s.manifest["name"], [Cell(p, fam) for p, fam in s.files(split)]


def run_cells(h, cells: list[Cell], k: int, seed: int, out: Path, resume: bool, bar,
              store=None) -> tuple[dict, BaseException | None]:
    """Run ``k`` trials of every cell on an open harness; returns ({file: RunResult}, error).

    :param store: (CellStore, row, group): the table's committed cells (trials.run_trials).
    """
    from racecav.evaluation.trials import run_trials

    results = {}
    for c in cells:
        ref = str(c.path.resolve())
        res, error = run_trials(h, ref, c.path.resolve(), k, seed, out / f"{c.path.stem}.jsonl", resume,
                                bar=bar, keep_trajectory=False,
                                store=None if store is None else (*store, c.path.name))
        results[c.path.name] = res
        if error is not None:
            return results, error
    return results, None


def family_summaries(cells: list[Cell], results: dict) -> tuple[object, dict]:
    """(overall Summary, {family: Summary}) over the finished trials."""
    from racecav.evaluation.results import summarize

    by_fam: dict[str, list] = {}
    for c in cells:
        r = results.get(c.path.name)
        by_fam.setdefault(c.family, []).extend(r.trials if r is not None else [])
    every = [t for trials in by_fam.values() for t in trials]
    return summarize(every), {f: summarize(t) for f, t in by_fam.items()}


def suite_json(name: str, split: str, controller: str, k: int, seed: int, cells: list[Cell], results: dict,
               wall_s: float, error) -> dict:
    """The results document of one controller over a suite split."""
    from racecav.common.bench import git_commit

    overall, fams = family_summaries(cells, results)
    return {"suite": name, "split": split, "controller": controller, "trials_per_scenario": k, "base_seed": seed,
            "git_commit": git_commit(), "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "complete": error is None and all(c.path.name in results and results[c.path.name].complete
                                              for c in cells),
            "stopped_reason": "" if error is None else f"{type(error).__name__}: {error}",
            "wall_s": round(wall_s, 1),
            "compute_charge_ms": sorted({r.controller.compute_charge_ms for r in results.values()},
                                        key=lambda v: (v is None, v or 0.0)),
            # the policy file each trial ran (--model or the shipped weights; none for the references)
            "weights_sha256": sorted({r.controller.weights_sha256 or "" for r in results.values()}),
            "summary": overall.model_dump(mode="json"),
            "families": {f: s.model_dump(mode="json") for f, s in fams.items()},
            "scenarios": [{"file": c.path.name, "family": c.family,
                           "trials": results[c.path.name].summary.trials if c.path.name in results else 0,
                           "successes": results[c.path.name].summary.successes if c.path.name in results else 0}
                          for c in cells]}


def run_suite(args, cfg) -> int:
    """``racecav eval --suite S --controller C``."""
    from tqdm import tqdm

    from racecav.evaluation.trials import Interrupted, NoBar, eval_perturb, with_model
    from racecav.evaluation.harness import CONTROLLERS, Harness, HarnessError, missing, perturbed
    from racecav.evaluation.plots import plot_success_bars

    k = args.trials_per_scenario
    if k < 1:
        print("racecav eval: --trials-per-scenario must be >= 1", file=sys.stderr)
        return 2
    try:
        name, cells = suite_cells(args.suite, args.split)
    except ValueError as e:
        print(f"racecav eval: {e}", file=sys.stderr)
        return 2
    try:  # --model: another policy file in the drl-* controller (a checkpoint before shipping)
        ctrl = with_model(CONTROLLERS[args.controller], getattr(args, "model", None))
    except ValueError as e:
        print(f"racecav eval: {e}", file=sys.stderr)
        return 2
    why = missing(ctrl)
    if why:
        print(f"racecav eval: cannot evaluate {ctrl.name}: {why}", file=sys.stderr)
        return 2
    try:  # --perturb: the controller's results are named CONTROLLER@PERTURBATION, as for one scenario
        perturb = eval_perturb(args, cfg)
    except ValueError as e:
        print(f"racecav eval: {e}", file=sys.stderr)
        return 2
    ctrl = perturbed(ctrl, perturb)
    seed = args.seed if args.seed is not None else 0
    out = args.out_dir / f"suite-{name}-{args.split}" / ctrl.name
    json_path = args.json or out.parent / f"{out.name}.json"  # a perturbed name holds dots (=0.0175)
    bar = NoBar() if args.no_progress else tqdm(total=len(cells) * k, unit="trial", dynamic_ncols=True,
                                                 desc=f"{ctrl.name} {name}/{args.split}", mininterval=1.0)
    wall0 = time.monotonic()
    results, error = {}, None
    try:
        if getattr(args, "ray", None) is not None:  # the files in chunks, each a Ray task (evaluation/ray_cells.py)
            from racecav.evaluation import ray_cells

            bar.close()  # ray_cells has its own
            results, why = ray_cells.run_suite(args, cells, out, perturb)
            error = RuntimeError(why) if why else None
        else:
            with Harness(cfg, ctrl, args.mode, str(cells[0].path.resolve()), out / "logs", args.real_time_factor,
                         compute_charge=getattr(args, "compute_charge", "fixed"), perturb=perturb) as h:
                results, error = run_cells(h, cells, k, seed, out, args.resume, bar)
    except HarnessError as e:
        error = e
    except (Interrupted, KeyboardInterrupt) as e:
        error = e
    finally:
        bar.close()
    doc = suite_json(name, args.split, ctrl.name, k, seed, cells, results, time.monotonic() - wall0, error)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(doc, indent=1) + "\n")
    fams = doc["families"]
    rows = [(ctrl.label, [(s["success_rate"], tuple(s["ci95"]) if s["ci95"] else None, None)
                          for s in fams.values()])]
    plot = plot_success_bars(rows, list(fams), args.plot or json_path.with_suffix(".png"),
                             title=f"{ctrl.label} on suite {name} ({args.split}), {k} trials per file (95 % CI)")
    for fam, s in fams.items():
        print(f"  {fam:18s} {_cell(s)}")
    print(f"{ctrl.label} on suite {name}/{args.split}: {_cell(doc['summary'])}")
    print(f"results: {json_path}; chart: {plot}")
    if error is not None:
        print(f"PARTIAL: {error}; continue with the same command and --resume", file=sys.stderr)
        return 130 if isinstance(error, (Interrupted, KeyboardInterrupt)) else 1
    return 0


def _cell(s: dict) -> str:
    if not s["trials"]:
        return "no trials"
    lo, hi = s["ci95"]
    return (f"{100 * s['success_rate']:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}] ({s['successes']}/{s['trials']}, "
            f"{s['collisions']} collisions)" + measures_text(s))


def measures_text(s: dict) -> str:
    """The benchmark's measures of a summary (results.Summary as a dict), "" when none recorded."""
    n = s.get("measured") or 0
    if not n:
        return ""
    text = (f"; frozen {s['frozen']}/{n}, driving score {s['mean_driving_score']:.2f}, "
            f"route {100 * s['mean_route_completion']:.0f} %")
    if s["collisions"]:
        text += (f", impact median {s['median_impact_speed_mps']:.2f} m/s (Euro NCAP bands "
                 + "/".join(str(b) for b in s["impact_bands"]) + ")")
    if s["from_rest"]:
        off = s["median_drive_off_s"]
        text += (f", from rest {s['from_rest']}: never drove off {s['never_drove_off']}, drive-off median "
                 + ("n/a" if off is None else f"{off:.2f} s"))
    return text
