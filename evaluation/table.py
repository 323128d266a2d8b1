"""``racecav eval --table``: the paper's Table 1 regenerated, written to docs/results.md.

Every controller runs the three intersection scenarios, N seeded trials each (the same seeds
for every controller: paired trials), their conflict-timed versions, the conflict suite's test
split and the open suite's (free intersections), through the real services (one harness per
controller: router + sim + controller processes; the scenario switches through the sim's
queryable). Each cell keeps its per-trial JSONL under runs/eval/table/, so ``--resume`` continues
an interrupted table; cells that did not finish are marked partial in the document. Every
complete cell also goes to the committed store (evaluation/store.py, docs/results-data/), which
``--resume`` reuses: a fresh clone rewrites the document without rerunning what is stored.

``--safety on`` runs every controller with the emergency-brake supervisor (``racecav safety``, a
brake input of the sim's mux), ``--safety both`` without and with it on the same seeds: the
document then gets the supervisor's on/off table (success and collisions per cell).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import sys
import time
from pathlib import Path

from racecav.common import registry
from racecav.common.config import Config
from racecav.evaluation.store import CellStore, code_drift, drift_text

SCENARIOS = registry.PAPER_SCENARIOS
CONFLICT = registry.CONFLICT_SCENARIOS
SHORT = registry.SHORT
PAPER_TABLE1 = registry.PAPER_TABLE1
SECTIONS = ("table1", "conflict", "suite", "free", "roads")
OPTIONAL_SECTIONS = ("robust",)
"""Sections run only when --sections names them (robust: evaluation/robust.py)."""
IMG_DIR = Path("docs/img")
# the suite sections: (suite, its `racecav suite generate` --n, --n-train, --seed), made on first use
# exactly as docs/world.md documents them; --suite replaces the conflict suite
SUITE_SECTIONS = {"suite": ("conflicts", 140, 1400, 0), "free": ("open", 20, 200, 3)}
ROADS_SUITE = "roads"
"""The generalization section's suite (`racecav suite generate --name roads`): every split of its
manifest but train (test, ood, controls), per family; its evaluation splits are generated first
when they are missing, and the section is skipped (with a message) when that cannot be done."""
STORE_NAME = "results-data"  # the committed cell store, beside the document (evaluation/store.py)


def _label(key: str) -> str:
    """Row label of a controller key: NAME, or NAME+safety for a run with the supervisor."""
    from racecav.evaluation.harness import CONTROLLERS

    base, plus, _ = key.partition("+safety")
    return CONTROLLERS[base].label + (" + safety" if plus else "")


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.0f}"


def _seed_text(seeds: dict) -> str:
    if len(set(seeds.values())) == 1:
        return str(next(iter(seeds.values())))
    return "(" + ", ".join(f"{SHORT[s]} {v}" for s, v in seeds.items()) + ")"


def cell_text(res) -> str:
    s = res.summary
    if not s.trials:
        return "not run"
    lo, hi = s.ci95
    text = f"**{100 * s.success_rate:.0f}** [{100 * lo:.0f}, {100 * hi:.0f}]"
    if not res.complete:
        text += f" PARTIAL {s.trials}/{res.trials_requested}"
    return text


def run_table(args: argparse.Namespace, cfg: Config) -> int:
    from tqdm import tqdm

    from racecav.common.scenario import SCENARIOS_DIR, load_scenario
    from racecav.evaluation.trials import NoBar, run_trials, write_json
    from racecav.evaluation.harness import CONTROLLERS, Harness, HarnessError, missing

    names = [c.strip() for c in (args.controllers or ",".join(registry.DEFAULT_TABLE)).split(",") if c.strip()]
    if not args.controllers:  # the default list: a policy not shipped yet is left out, not an error
        names = [n for n in names if n in CONTROLLERS and not missing(CONTROLLERS[n])]
    sections = [x.strip() for x in (args.sections or ",".join(SECTIONS)).split(",") if x.strip()]
    if getattr(args, "jobs", 1) < 1:
        print("racecav eval --table: --jobs must be >= 1", file=sys.stderr)
        return 2
    if set(sections) - set(SECTIONS + OPTIONAL_SECTIONS):
        print(f"racecav eval --table: unknown section(s) {sorted(set(sections) - set(SECTIONS + OPTIONAL_SECTIONS))}; "
              f"known: {SECTIONS + OPTIONAL_SECTIONS}", file=sys.stderr)
        return 2
    if "robust" in sections:
        from racecav.evaluation import robust

        if args.robust_trials < 1:
            print("racecav eval --table: --robust-trials must be >= 1", file=sys.stderr)
            return 2
        if robust.suite_trials(args) < 0:
            print("racecav eval --table: --robust-suite-trials must be >= 0 (0: no suite part)", file=sys.stderr)
            return 2
        bad = [n for n in robust.controllers(args) if n not in CONTROLLERS]
        if bad:
            print(f"racecav eval --table: unknown --robust-controllers {bad}; known: {sorted(CONTROLLERS)}",
                  file=sys.stderr)
            return 2
    unknown = [n for n in names if n not in CONTROLLERS]
    if unknown:
        print(f"racecav eval --table: unknown controller(s) {unknown}; known: {sorted(CONTROLLERS)}", file=sys.stderr)
        return 2
    absent = {n: missing(CONTROLLERS[n]) for n in names if missing(CONTROLLERS[n])}
    if absent:
        for n, why in absent.items():
            print(f"racecav eval --table: cannot evaluate {n}: {why}", file=sys.stderr)
        print("(evaluate the others with --controllers " + ",".join(n for n in names if n not in absent) + ")",
              file=sys.stderr)
        return 2
    suites: dict[str, tuple[str, list]] = {}  # section -> (suite name, test cells)
    robust_suite = None  # the robust section's suite part: the suite section's (suite name, test cells)
    try:
        for sec in (x for x in SUITE_SECTIONS if x in sections):
            suites[sec] = suite_split(sec, args)
        if "robust" in sections and robust.suite_trials(args) > 0:
            robust_suite = suites.get("suite") or suite_split("suite", args)
    except ValueError as e:
        print(f"racecav eval --table: {e}", file=sys.stderr)
        return 2
    safety = getattr(args, "safety", "off")
    runs = [(n, on) for n in names for on in {"off": (False,), "on": (True,), "both": (False, True)}[safety]]
    roads: dict[str, tuple[str, list]] = {}  # split -> (suite name, cells): the generalization section
    roads_rows: set[tuple[str, bool]] = set()
    if "roads" in sections:
        roads, why = roads_splits(getattr(args, "roads_suite", None) or ROADS_SUITE, progress=not args.no_progress)
        if why:
            print(f"racecav eval --table: section roads skipped: {why}", file=sys.stderr)
        rn = getattr(args, "roads_controllers", None)
        picked = names if rn is None else [c.strip() for c in rn.split(",") if c.strip() and c.strip() != "none"]
        bad = [n for n in picked if n not in names]
        if bad:
            print(f"racecav eval --table: --roads-controllers {bad}: not among the table's controllers {names}",
                  file=sys.stderr)
            return 2
        # the main tables' rows only (with --safety both: without the supervisor)
        roads_rows = {(n, on) for n, on in runs if roads and n in picked and on == (safety == "on")}
    trials = args.trials if args.trials is not None else 100
    if trials < 1:
        print("racecav eval: --trials must be >= 1", file=sys.stderr)
        return 2
    out = args.out_dir / "table"
    scen = (list(SCENARIOS) if "table1" in sections else []) + (list(CONFLICT) if "conflict" in sections else [])
    seeds = {s: (args.seed if args.seed is not None else load_scenario(s).seed) for s in scen}
    k_suite = args.trials_per_scenario
    from_store = getattr(args, "from_store", False)
    if from_store:
        args.resume = True
    try:
        store = CellStore(_store_dir(args))
        cells = {(n, on): _row_cells(n, on, scen, seeds, trials, suites, k_suite, args, out, store,
                                     roads if (n, on) in roads_rows else {}) for n, on in runs}
        robust_rows = robust.plan(args, store, out, robust_suite) if "robust" in sections and not from_store else []
    except ValueError as e:  # a broken store file
        print(f"racecav eval --table: {e}", file=sys.stderr)
        return 2
    if from_store:  # nothing is run: name what a run would have to add
        lacking = {n + ("+safety" if on else ""): [c.cell for c in cs if c.stored is None]
                   for (n, on), cs in cells.items()}
        for row, cs in ((r, cs) for r, cs in lacking.items() if cs):
            print(f"racecav eval --table --from-store: {_store_dir(args)} holds no current cell for {len(cs)} "
                  f"of {row}'s cells (e.g. {', '.join(cs[:3])}; absent, or stored with another trial count, "
                  "scenario file or weights): measure them with --resume instead of --from-store", file=sys.stderr)
        if "robust" in sections:
            _, _, lack = robust.run(args, cfg, store, out, from_store=True, suite=robust_suite)
            if lack:
                print(f"racecav eval --table --from-store: {_store_dir(args)} holds no current robust cell for "
                      f"{len(lack)} cells (e.g. {', '.join(lack[:3])}; absent, or stored with another trial count, "
                      "scenario file or weights): measure them with --resume instead of --from-store", file=sys.stderr)
                return 2
        if any(lacking.values()):
            return 2
    commits: dict[str, int] = {}  # the code the reused cells were measured with
    results: dict[tuple[str, str], object] = {}
    suite_results: dict[str, dict[str, dict]] = {sec: {} for sec in suites}
    roads_results: dict[str, dict[str, dict]] = {split: {} for split in roads}
    wall0 = time.monotonic()
    error = None
    per_run = {r: sum(c.trials for c in cs) for r, cs in cells.items()}
    total = sum(per_run.values())
    robust_todo = [r for r in robust_rows if r.todo]  # the robust section's rows with a cell to measure
    # the one dispatch point: --ray, --jobs N or this process (the robust rows: robust.run, below)
    jobs = min(getattr(args, "jobs", 1), len(runs) + len({r.name for r in robust_todo}))
    ray = getattr(args, "ray", None) is not None and not from_store
    if jobs > 1 or ray:  # the cells are computed elsewhere; the pass below reads them and writes the doc
        if ray:  # Ray tasks, one per cell (evaluation/ray_cells.py)
            from racecav.evaluation import ray_cells

            every = [c for cs in cells.values() for c in cs]
            rc = ray_cells.run_table(args, runs, cells, seeds, {**suites, **{f"roads/{k}": v for k, v in roads.items()}},
                                     store, total + sum(c.trials for r in robust_rows for c in r.cells),
                                     (_done(every) + _done([c for r in robust_rows for c in r.cells])) if args.resume
                                     else 0, robust_todo)
        else:  # child tables, one per row
            rc = _run_jobs(args, runs, jobs, trials, sections, cells, per_run, out, total, roads_rows, robust_todo)
        if rc != 0:
            return rc
        args.resume = True
        cells = {(n, on): _row_cells(n, on, scen, seeds, trials, suites, k_suite, args, out, store,
                                     roads if (n, on) in roads_rows else {}) for n, on in runs}
    bar = NoBar() if args.no_progress else tqdm(total=total, unit="trial", desc="table", dynamic_ncols=True,
                                                 mininterval=1.0)
    try:
        for name, on in (runs if per_run else []):
            ctrl = CONTROLLERS[name]
            key = name + ("+safety" if on else "")  # as run_trials names it
            bar.set_description_str(key)
            if all(c.stored is not None for c in cells[(name, on)]):  # a committed row: no services needed
                for c in cells[(name, on)]:
                    bar.update(c.trials)
                    if c.section.startswith("roads/"):
                        roads_results[c.section[6:]].setdefault(key, {})[c.cell] = c.stored
                    elif c.section in suites:
                        suite_results[c.section].setdefault(key, {})[c.cell] = c.stored
                    else:
                        results[(key, c.cell)] = c.stored
                        write_json(c.stored, out / f"{_stem(name, c.cell, args.mode, on)}.json")
                continue
            every_suite = [*suites.values(), *(roads.values() if (name, on) in roads_rows else ())]
            first = scen[0] if scen else str(every_suite[0][1][0].path.resolve())
            try:
                with Harness(cfg, ctrl, args.mode, first, out / "logs" / key, args.real_time_factor, safety=on,
                             compute_charge=getattr(args, "compute_charge", "fixed")) as h:
                    for sc in scen:
                        stem = _stem(name, sc, args.mode, on)
                        res, error = run_trials(h, sc, SCENARIOS_DIR / f"{sc}.toml", trials, seeds[sc],
                                                out / f"{stem}.jsonl", args.resume, bar=bar,
                                                store=(store, key, "scenarios", sc))
                        results[(key, sc)] = res
                        write_json(res, out / f"{stem}.json")
                        if error is not None:
                            raise error
                    for sec, (suite_name, suite_cells_) in suites.items():
                        from racecav.evaluation.suite_eval import run_cells

                        suite_results[sec][key], error = run_cells(
                            h, suite_cells_, k_suite, args.seed or 0, out / f"suite-{suite_name}" / key,
                            args.resume, bar, store=(store, key, f"suite-{suite_name}"))
                        if error is not None:
                            raise error
                    for split, (suite_name, split_cells) in (roads.items() if (name, on) in roads_rows else ()):
                        from racecav.evaluation.suite_eval import run_cells

                        roads_results[split][key], error = run_cells(
                            h, split_cells, k_suite, args.seed or 0, out / f"suite-{suite_name}-{split}" / key,
                            args.resume, bar, store=(store, key, f"suite-{suite_name}-{split}"))
                        if error is not None:
                            raise error
            except HarnessError as e:
                error = e
                break
    except BaseException as e:  # interrupted: write what we have, marked partial
        error = e
    finally:
        bar.close()
    robust_results: dict = {}
    if "robust" in sections and error is None:
        robust_results, error, _ = robust.run(args, cfg, store, out, from_store, suite=robust_suite)
        for c in robust_results.values():
            if c.complete:
                commits[c.git_commit] = commits.get(c.git_commit, 0) + 1
    wall = time.monotonic() - wall0
    docs: dict[str, dict] = {}
    for sec, (suite_name, suite_cells_) in suites.items():
        from racecav.evaluation.suite_eval import suite_json

        # wall: the trials' own, summed (cells may come from several resumed invocations)
        docs[sec] = {n: suite_json(suite_name, "test", n, k_suite, args.seed or 0, suite_cells_, r,
                                   sum(t.wall_s for c in r.values() for t in c.trials), None)
                     for n, r in suite_results[sec].items()}
        for n, doc_ in docs[sec].items():
            (out / f"suite-{suite_name}").mkdir(parents=True, exist_ok=True)
            (out / f"suite-{suite_name}" / f"{n}.json").write_text(json.dumps(doc_, indent=1) + "\n")
    roads_docs: dict[str, dict] = {}  # split -> {row: suite_json}
    for split, (suite_name, split_cells) in roads.items():
        from racecav.evaluation.suite_eval import suite_json

        roads_docs[split] = {n: suite_json(suite_name, split, n, k_suite, args.seed or 0, split_cells, r,
                                           sum(t.wall_s for c in r.values() for t in c.trials), None)
                             for n, r in roads_results[split].items()}
        for n, doc_ in roads_docs[split].items():
            (out / f"suite-{suite_name}-{split}").mkdir(parents=True, exist_ok=True)
            (out / f"suite-{suite_name}-{split}" / f"{n}.json").write_text(json.dumps(doc_, indent=1) + "\n")
    for c in (c for cs in cells.values() for c in cs if c.stored is not None):
        commits[c.stored.git_commit] = commits.get(c.stored.git_commit, 0) + 1
    provenance = drift_text(commits, code_drift(commits))
    if provenance:
        print(f"racecav eval --table: {provenance}", file=sys.stderr)
    keys_ = [n + ("+safety" if safety == "on" else "") for n in names]  # the main tables' rows
    doc = write_results_doc(results, keys_, trials, seeds, args, wall, error, sections=sections,
                            suite=docs.get("suite"), free=docs.get("free"), provenance=provenance,
                            roads=(roads, roads_docs) if roads_docs else None,
                            robust_results=robust_results if "robust" in sections else None,
                            robust_suite=robust_suite)
    for name in keys_:
        cells = [results.get((name, sc)) for sc in SCENARIOS]
        print(f"{_label(name):34s} " + "  ".join(
            f"{SHORT[sc]} {cell_text(r) if r else 'not run':28s}" for sc, r in zip(SCENARIOS, cells)))
    print(f"wrote {doc} ({wall / 60:.1f} min)")
    if error is not None:
        print(f"PARTIAL table: {error}; continue with the same command and --resume", file=sys.stderr)
        return 130 if isinstance(error, KeyboardInterrupt) or type(error).__name__ == "Interrupted" else 1
    return 0


def suite_split(sec: str, args) -> tuple[str, list]:
    """(suite name, test cells) of a suite section (SUITE_SECTIONS; ``--suite`` replaces the conflict
    suite), generated first as docs/world.md documents it when it is missing.

    :raises ValueError: no such suite or split."""
    from racecav.common.scenario import SUITES_RUNS_DIR
    from racecav.evaluation import suite as S
    from racecav.evaluation.suite_eval import suite_cells

    spec, n, n_train, seed = SUITE_SECTIONS[sec]
    if sec == "suite" and args.suite is not None:
        spec = args.suite
    elif not (SUITES_RUNS_DIR / spec / "suite.json").is_file():
        # the test split alone: its files are the ones a full generation writes (training adds train)
        print(f"racecav eval --table: generating the {spec} suite's test split first "
              f"(racecav suite generate --name {spec} --n {n} --n-train {n_train} --seed {seed} --splits test)")
        S.generate(S.load_families(spec), SUITES_RUNS_DIR / spec, n, n_train, seed, progress=not args.no_progress,
                   splits=("test",))
    return suite_cells(spec, "test")


@dataclasses.dataclass(frozen=True)
class RowCell:
    """One cell of a table row: a scenario ("scenarios" section) or a suite section's file."""

    section: str
    cell: str
    """The scenario's name, or the suite file's name."""
    trials: int
    jsonl: Path
    """Its resumable per-trial records under --out-dir."""
    stored: object = None
    """The committed complete cell (RunResult) when --resume may use it, else None."""


def _row_cells(name: str, on: bool, scen: list[str], seeds: dict, trials: int, suites: dict, k: int, args,
               out: Path, store: CellStore, roads: dict | None = None) -> list[RowCell]:
    """Every cell of the row (controller ``name``, supervisor ``on``), with what the store holds of it;
    ``roads``: split -> (suite name, cells) of the generalization section when the row has it."""
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.evaluation.harness import CONTROLLERS
    from racecav.evaluation.trials import cell_key

    ctrl, row = CONTROLLERS[name], name + ("+safety" if on else "")
    seed = args.seed or 0

    def stored(group: str, cell: str, path: Path, base_seed: int, n: int):
        if not args.resume:
            return None
        return store.get(row, group, cell, cell_key(ctrl, on, args.mode, path, base_seed), n)

    cells = [RowCell("scenarios", sc, trials, out / f"{_stem(name, sc, args.mode, on)}.jsonl",
                     stored("scenarios", sc, SCENARIOS_DIR / f"{sc}.toml", seeds[sc], trials)) for sc in scen]
    for sec, (suite_name, files) in suites.items():
        cells += [RowCell(sec, c.path.name, k, out / f"suite-{suite_name}" / row / f"{c.path.stem}.jsonl",
                          stored(f"suite-{suite_name}", c.path.name, c.path.resolve(), seed, k)) for c in files]
    for split, (suite_name, files) in (roads or {}).items():
        group = f"suite-{suite_name}-{split}"
        cells += [RowCell(f"roads/{split}", c.path.name, k, out / group / row / f"{c.path.stem}.jsonl",
                          stored(group, c.path.name, c.path.resolve(), seed, k)) for c in files]
    return cells


def roads_splits(spec: str, progress: bool = True) -> tuple[dict[str, tuple[str, list]], str]:
    """The generalization section's splits: ({split: (suite name, cells)} of every split of the suite's
    manifest but train, in its order; why it is skipped, or "").

    The roads suite is generated first, as the suite sections' are, when it is missing and its suite
    file (common/data/suites/roads.toml) exists: a fresh clone rewrites the section from the store."""
    from racecav.common import procs
    from racecav.common.scenario import open_suite
    from racecav.evaluation.suite import SUITES_DIR
    from racecav.evaluation.suite_eval import suite_cells

    try:
        suite = open_suite(spec)
    except ValueError as e:
        if spec != ROADS_SUITE or not (SUITES_DIR / f"{spec}.toml").is_file():
            return {}, str(e)
        import subprocess

        cmd = ["suite", "generate", "--name", spec, "--splits", "test,ood,controls"]  # train: for training only
        print(f"racecav eval --table: generating the {spec} suite's evaluation splits first (racecav "
              f"{' '.join(cmd)})", flush=True)
        r = subprocess.run(procs.racecav_cmd(*cmd, *(() if progress else ("--no-progress",))),
                           stdout=None if progress else subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if r.returncode != 0:
            return {}, f"`racecav suite generate --name {spec}` failed: {(r.stderr.strip().splitlines() or [''])[-1]}"
        try:
            suite = open_suite(spec)
        except ValueError as e2:
            return {}, str(e2)
    splits = [sp for sp in suite.manifest.get("splits", {}) if sp != "train"]
    if not splits:
        return {}, f"suite {spec} has no split but train"
    return {sp: suite_cells(spec, sp) for sp in splits}, ""


def _done(cells: list[RowCell]) -> int:
    """Trials a row already has: its stored cells whole, the others' JSONL lines."""
    return sum(c.trials if c.stored is not None else min(_lines(c.jsonl), c.trials) for c in cells)


def _stem(name: str, sc: str, mode: str, on: bool) -> str:
    """A cell's file stem in OUT/table (its .json and resumable .jsonl)."""
    return f"{name}-{sc}" + ("" if mode == "lockstep" else f"-{mode}") + ("-safety" if on else "")


def _store_dir(args) -> Path:
    """--store, default docs/results-data beside the document."""
    return (getattr(args, "store", None) or Path(args.doc).parent / STORE_NAME).resolve()


def _lines(path: Path) -> int:
    """Trials on disk in a JSONL file (one line each); 0 if there is none."""
    if not path.is_file():
        return 0
    with open(path, "rb") as f:
        return sum(1 for _ in f)


def _run_jobs(args, runs: list[tuple[str, bool]], jobs: int, trials: int, sections: list[str], cells: dict,
              per_run: dict, out: Path, total: int, roads_rows: set = frozenset(), robust_rows: list = ()) -> int:
    """``--jobs N``: a pool of N child ``racecav eval --table`` processes (each with its own router,
    sim and controller: about one core each), one per (controller, safety) row and one per
    controller of the robust section with cells left (``robust_rows``: robust.Row), the rows with
    the most trials left first, so that the pool ends on short ones and no core idles for long. They
    write the same cells one process would (and the same store). Returns 0 once every child
    finished its cells; otherwise the first failing child's code (its output: OUT/table/logs/job-K.log)."""
    import os

    from tqdm import tqdm

    from racecav.common import procs

    base = ["eval", "--table", "--trials", str(trials), "--trials-per-scenario", str(args.trials_per_scenario),
            "--mode", args.mode, "--real-time-factor", str(args.real_time_factor),
            "--out-dir", str(args.out_dir), "--no-progress",
            "--compute-charge", getattr(args, "compute_charge", "fixed")]
    for flag, value in (("--seed", args.seed), ("--suite", args.suite), ("--config", getattr(args, "config", None)),
                        ("--roads-suite", getattr(args, "roads_suite", None))):
        if value is not None:
            base += [flag, str(value)]
    if args.resume:
        base.append("--resume")
    (out / "logs").mkdir(parents=True, exist_ok=True)
    rows = []  # (trials left, row key, the child's own flags)
    table_sections = ",".join(s for s in sections if s not in OPTIONAL_SECTIONS)
    for name, on in runs:
        key = name + ("+safety" if on else "")
        done = _done(cells[(name, on)]) if args.resume else 0  # else every cell starts over
        if per_run[(name, on)] - done > 0:
            rows.append((per_run[(name, on)] - done, key,
                         ["--sections", table_sections, "--safety", "on" if on else "off", "--controllers", name,
                          "--roads-controllers", name if (name, on) in roads_rows else "none"]))
    for name in dict.fromkeys(r.name for r in robust_rows):  # the robust section: a child per controller
        todo = [c for r in robust_rows if r.name == name for c in r.todo]
        rows.append((sum(c.trials for c in todo) - (_done(todo) if args.resume else 0), f"{name} (robust)",
                     ["--sections", "robust", "--safety", "off", "--controllers", name, "--robust-controllers", name,
                      "--robust-trials", str(args.robust_trials),
                      "--robust-suite-trials", str(getattr(args, "robust_suite_trials", 0))]))
    rows.sort(key=lambda r: -r[0])  # stable: equal rows keep the --controllers order
    pending = list(enumerate(rows))
    running: dict[int, object] = {}
    failed: list[tuple[int, str, int]] = []
    every = [c for row in cells.values() for c in row] + [c for r in robust_rows for c in r.cells]
    total += sum(c.trials for r in robust_rows for c in r.cells)
    bar = None if args.no_progress else tqdm(total=total, initial=_done(every), unit="trial",
                                             desc=f"table ({jobs} jobs)", dynamic_ncols=True)
    try:
        while pending or running:
            while pending and len(running) < jobs:
                k, (left, key, own) = pending.pop(0)
                log_path = out / "logs" / f"job-{k}.log"
                running[k] = procs.start(base + own + ["--doc", str(out / "logs" / f"job-{k}.md"),
                                                       "--store", str(_store_dir(args))],
                                         dict(os.environ), log_path)
                print(f"racecav eval --table --jobs {jobs}: job {k}: {key}, {left} trials (log {log_path})",
                      flush=True)
            time.sleep(2.0)  # the bar re-counts every JSONL line: not more often
            for k, c in list(running.items()):
                if c.poll() is not None:
                    del running[k]
                    if c.returncode != 0:
                        failed.append((k, rows[k][1], c.returncode))
            if bar is not None:
                bar.n = _done(every)
                bar.refresh()
    except BaseException as e:  # interrupted: the children stop too (their cells stay resumable)
        for c in running.values():
            procs.stop(c)
        print(f"PARTIAL table: {type(e).__name__}; continue with the same command and --resume", file=sys.stderr)
        return 130
    finally:
        if bar is not None:
            bar.close()
    for k, key, rc in failed:
        print(f"racecav eval --table: job {k} ({key}) exited with code {rc}; see "
              f"{out / 'logs' / f'job-{k}.log'}; continue with the same command and --resume", file=sys.stderr)
    return failed[0][2] if failed else 0


def write_results_doc(results: dict, names: list[str], trials: int, seeds: dict, args, wall_s: float,
                      error, sections=SECTIONS, suite: dict | None = None, free: dict | None = None,
                      provenance: str = "", roads: tuple[dict, dict] | None = None,
                      robust_results: dict | None = None, robust_suite: tuple[str, list] | None = None) -> Path:
    """docs/results.md: the table beside the paper's, latencies, the bar chart and Figure 4;
    ``provenance``: store.drift_text of the reused cells, in the header."""
    from racecav.common.bench import machine
    from racecav.common.scenario import load_scenario
    from racecav.common.vehicle import load_car
    from racecav.common.bench import git_commit
    from racecav.evaluation.plots import plot_success_bars, plot_trajectories

    doc = Path(args.doc)
    img = doc.parent / "img"
    cmd = "racecav eval --table" + (f" --trials {trials}" if trials != 100 else "")
    if args.sections:
        cmd += f" --sections {args.sections}"
    if suite and args.suite:
        cmd += f" --suite {args.suite}"
    if getattr(args, "trials_per_scenario", 5) != 5:
        cmd += f" --trials-per-scenario {args.trials_per_scenario}"
    if args.controllers:
        cmd += f" --controllers {args.controllers}"
    if roads and getattr(args, "roads_controllers", None):
        cmd += f" --roads-controllers {args.roads_controllers}"
    if roads and getattr(args, "roads_suite", None):
        cmd += f" --roads-suite {args.roads_suite}"
    if args.mode != "lockstep":
        cmd += f" --mode {args.mode}"
    if getattr(args, "safety", "off") != "off":
        cmd += f" --safety {args.safety}"
    if robust_results is not None:
        from racecav.evaluation import robust

        if args.robust_trials != 30:
            cmd += f" --robust-trials {args.robust_trials}"
        if robust.suite_trials(args) != 1:
            cmd += f" --robust-suite-trials {robust.suite_trials(args)}"
        if robust.controllers(args) != robust.controllers(None):
            cmd += f" --robust-controllers {','.join(robust.controllers(args))}"
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    trial_wall = sum(t.wall_s for r in results.values() for t in r.trials) \
        + sum(d["wall_s"] for sec in (suite, free) if sec for d in sec.values())  # the suite sections' too
    lines = [
        "# Results: collision-avoidance success (the paper's Table 1), latency, trajectories",
        "",
        (f"Written by `{cmd}` on {stamp}, {machine()}, commit {git_commit()}, "
         + (f"from the committed cells alone (`--from-store`; their trials took {trial_wall / 60:.1f} min in the "
            "invocations that ran them)" if getattr(args, "from_store", False) else
            f"wall time {wall_s / 60:.1f} min (trials alone: {trial_wall / 60:.1f} min, whichever invocation ran "
            "them)") + ". Nothing here is typed by hand."),
        "",
    ]
    if provenance:
        lines += [provenance, ""]
    if error is not None:
        lines += [f"**PARTIAL**: the run stopped early ({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}); "
                  "cells marked PARTIAL hold fewer trials than requested.", ""]
    lines += [
        "## Success rate (%) with 95 % Wilson interval, beside the paper",
        "",
        f"Ours: PyBullet sim service (`racecav sim --mode {args.mode}`) driven over Zenoh by the controller "
        f"service, {trials} seeded trials per cell (trial i uses seed {_seed_text(seeds)} + i; the same seeds for "
        "every controller). Paper: 10 trials on the 1/10-scale car.",
        "",
        "| controller | " + " | ".join(f"{SHORT[s]} ours | {SHORT[s]} paper" for s in SCENARIOS) + " |",
        "|---|" + "---:|---:|" * len(SCENARIOS),
    ]
    for n in names:
        paper = PAPER_TABLE1.get(n)
        cells = []
        for k, sc in enumerate(SCENARIOS):
            r = results.get((n, sc))
            cells += [cell_text(r) if r else "not run", _pct(paper[k]) if paper else "-"]
        lines.append(f"| {_label(n)} | " + " | ".join(cells) + " |")
    lines += ["", "Success = no contact during the scenario's duration and at least its `min_progress_m` of "
              "progress along the ego's road (common/scenario.py). \"No evasion\" drives straight at 1 m/s: it "
              "shows how many trials are real conflicts. \"Full throttle\" drives straight at the agent's "
              "top speed (2.7 m/s, about the DRL policies' speed) and the MPC-APF at v_ref 2.7 m/s cruises "
              "at it: in the side scenarios an ego that fast is through the crossing before the 1 m/s "
              "obstacle arrives, so there the speed a controller chooses decides most of the outcome; "
              "head-to-head needs an evasion at any speed. The trial seeds are those of the in-process report of "
              "the shipped policies (docs/training.md, `racecav train report`) and differ from the checkpoint-"
              "selection seeds; the two should agree up to the latency the bus and lockstep charge here.", ""]
    # bar chart
    rows = []
    for n in names:
        paper = PAPER_TABLE1.get(n)
        cells = []
        for k, sc in enumerate(SCENARIOS):
            r = results.get((n, sc))
            s = r.summary if r else None
            cells.append((s.success_rate if s else None, tuple(s.ci95) if s and s.ci95 else None,
                          paper[k] if paper else None))
        rows.append((_label(n), cells))
    bars = plot_success_bars(rows, [SHORT[s] for s in SCENARIOS], img / "results-table1.png",
                             title=f"Success rate, {trials} sim trials per cell (95 % CI) vs paper (10 hardware trials)")
    lines += [f"![success rates]({bars.relative_to(doc.parent)})", ""]
    # details: collisions, distances, latency
    lines += ["## Per cell: collisions, distance, progress, latency", "",
              "Latency: scan -> command, from a scan's arrival at the router to the arrival there of the "
              "command answering it (its `scan_seq`), both stamped by the router's clock (Zenoh timestamping): "
              "the controller's whole leg (two hops, decode, compute, publish), pooled over every step; compute: "
              "the controller's own `compute_ns`. In lockstep mode the sim applies each command its compute time "
              "into the control period (a slow controller pays for its slowness in sim time): by default the "
              "controller's benchmarked time (the registry's `charge_ms`, recorded per cell as "
              "`controller.compute_charge_ms`), so a cell repeats whatever the machine's load; cells with "
              "`compute_charge_ms: null` were charged their measured `compute_ns`.", "",
              "| controller | scenario | trials | success | collisions | median min gap (m) | mean progress (m) "
              "| scan->cmd median / p99 (ms) | compute median / p99 (ms) | trials wall (s) |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    f = lambda v, d=2: "n/a" if v is None else f"{v:.{d}f}"  # noqa: E731
    for n in names:
        for sc in SCENARIOS:
            r = results.get((n, sc))
            if r is None:
                continue
            s = r.summary
            lines.append(f"| {_label(n)} | {sc} | {s.trials} | {s.successes} | {s.collisions} | "
                         f"{f(s.median_min_gap_m)} | {f(s.mean_progress_m)} | {f(s.latency_ms.median, 3)} / "
                         f"{f(s.latency_ms.p99, 3)} | {f(s.compute_ms.median, 3)} / {f(s.compute_ms.p99, 3)} | "
                         f"{sum(t.wall_s for t in r.trials):.0f} |")
    lines += ["", "Paper, Table 2 (Jetson Orin AGX): DRL 30,466 FLOPs, 0.206 ms; MPC-APF 960,000 FLOPs, 13.2 ms "
              "(this machine's numbers: `racecav bench controllers`, docs/benchmarks.md).", ""]
    # Figure 4: one trial per scenario of the reversed-heading policy (or the first controller run)
    fig_ctrl = next((n for n in ("drl-reversed", *names) if all((n, s) in results and results[(n, s)].trials
                                                                  for s in SCENARIOS)), None)
    if fig_ctrl:
        car = load_car()
        panels = [(results[(fig_ctrl, s)].trials[0], f"({'abc'[k]}) {SHORT[s]}") for k, s in enumerate(SCENARIOS)]
        walls = [load_scenario(s).build_world().walls for s in SCENARIOS]
        fig = plot_trajectories(panels, walls, img / "results-fig4.png", car_size=(car.length, car.width),
                                title=f"{_label(fig_ctrl)}: trial 0 of each scenario (ego green, obstacle red, "
                                "darker = later; dotted = start, solid = end)")
        lines += ["## Trajectories (the paper's Figure 4)", "",
                  f"{_label(fig_ctrl)}, the first trial (by seed, not picked) of each scenario.", "",
                  f"![trajectories]({fig.relative_to(doc.parent)})", ""]
    lines += _conflict_sections(results, names, trials, seeds, {k: v for k, v in (suite or {}).items() if k in names},
                                img, doc)
    lines += _free_section({k: v for k, v in (free or {}).items() if k in names})
    lines += _safety_section(results, names, trials, suite or {}, free or {})
    if roads:
        from racecav.evaluation.roads_doc import roads_section

        lines += roads_section(*roads, img, doc, label=_label)
    if robust_results is not None:
        lines += robust.section(robust_results, args, img, doc, _label, robust_suite)
    lines += ["## Reproduce", "", f"```sh\n{cmd}            # --jobs N: N processes; --resume: continue an interrupted run\n"
              "racecav eval --scenario head-to-head --controller drl-reversed --trials 20 --plot h2h.png\n```", "",
              f"Per-trial records (JSONL) and results (JSON, schema docs/results-schema.json) of every cell: "
              f"{args.out_dir / 'table'}/. Every complete cell is also kept, compactly (no trajectories but "
              f"trial 0's, no per-step latencies; the summaries computed from the full data), in the committed "
              f"store {_store_dir(args).name}/ beside this document (evaluation/store.py): with `--resume` a fresh "
              "clone rewrites this document from it and runs only the cells it lacks (a new policy's weights, "
              "an edited scenario file); with `--from-store` it runs nothing and names the cells the store lacks "
              "(tests/test_eval_harness.py checks that this document is what the store writes).", ""]
    doc.parent.mkdir(parents=True, exist_ok=True)
    doc.write_text("\n".join(lines))
    return doc


def _rate_text(sm: dict) -> str:
    """A suite summary's success rate with its 95 % interval, as in cell_text."""
    if not sm["trials"]:
        return "not run"
    lo, hi = sm["ci95"]
    return f"**{100 * sm['success_rate']:.0f}** [{100 * lo:.0f}, {100 * hi:.0f}]"


def _conflict_sections(results: dict, names: list[str], trials: int, seeds: dict, suite: dict | None,
                       img: Path, doc: Path) -> list[str]:
    """docs/results.md: the conflict-timed paper scenarios and the suite's test split, per family."""
    from racecav.evaluation.plots import plot_success_bars

    lines: list[str] = []
    have = [n for n in names if any((n, c) in results for c in CONFLICT)]
    if have:
        lines += ["## Conflict-timed paper scenarios: avoidance, not speed", "",
                  "The same three scenarios with the obstacle timed by the ego (common/data/scenarios/conflict-*.toml): "
                  "it waits until the ego is 4 s from the crossing centre at its current speed, then re-solves its "
                  "speed every control period (0.5-2.0 m/s) to arrive there together with the ego, and holds its "
                  "speed once the ego is within 1.0 m or 0.8 s (sim/actors.py). A car that does not evade collides "
                  f"at any speed. {trials} trials per cell (trial i: seed {next(iter(seeds.values()), 0)} + i), "
                  "95 % Wilson intervals; the reference rows must be near 0.", "",
                  "| controller | " + " | ".join(f"{SHORT[s]} conflict" for s in SCENARIOS)
                  + " | collisions | median min gap (m) |",
                  "|---|" + "---:|" * (len(SCENARIOS) + 2)]
        rows = []
        for n in have:
            rs = [results.get((n, c)) for c in CONFLICT]
            cells = [cell_text(r) if r else "not run" for r in rs]
            coll = sum(r.summary.collisions for r in rs if r)
            gaps = [r.summary.median_min_gap_m for r in rs if r and r.summary.median_min_gap_m is not None]
            lines.append(f"| {_label(n)} | " + " | ".join(cells) + f" | {coll} | "
                         + ("/".join(f"{g:.2f}" for g in gaps) or "n/a") + " |")
            rows.append((_label(n), [(r.summary.success_rate, tuple(r.summary.ci95) if r.summary.ci95
                                                 else None, None) if r else (None, None, None) for r in rs]))
        chart = plot_success_bars(rows, [f"{SHORT[s]} conflict" for s in SCENARIOS], img / "results-conflict.png",
                                  title=f"Conflict-timed paper scenarios, {trials} sim trials per cell (95 % CI)")
        lines += ["", f"![conflict-timed]({chart.relative_to(doc.parent)})", ""]
    if suite:
        first = next(iter(suite.values()))
        fams = list(first["families"])
        lines += [f"## Conflict suite `{first['suite']}`, test split, per family", "",
                  f"`racecav suite generate --name {first['suite']}` (families: common/data/suites/"
                  f"{first['suite']}.toml, docs/world.md), test split: {len(first['scenarios'])} files, "
                  f"{first['trials_per_scenario']} trials each (trial i: seed {first['base_seed']} + i), through "
                  "the services like every cell here. Never used in training or selection (training: the train "
                  "split; selection: the train split with selection seeds). Success per family and overall, 95 % "
                  "Wilson intervals.", "",
                  "| controller | " + " | ".join(fams) + " | overall |", "|---|" + "---:|" * (len(fams) + 1)]
        rows = []
        for n, d in suite.items():
            lines.append(f"| {_label(n)} | " + " | ".join(_rate_text(d["families"][f]) for f in fams)
                         + f" | {_rate_text(d['summary'])} |")
            rows.append((_label(n), [(d["families"][f]["success_rate"],
                                                 tuple(d["families"][f]["ci95"]) if d["families"][f]["ci95"] else None,
                                                 None) for f in fams]))
        chart = plot_success_bars(rows, fams, img / "results-suite.png",
                                  title=f"Conflict suite {first['suite']} (test split), per family (95 % CI)")
        lines += ["", f"![suite]({chart.relative_to(doc.parent)})", "",
                  "| controller | trials | collisions | median min gap (m) | mean progress (m) |",
                  "|---|---:|---:|---:|---:|"]
        for n, d in suite.items():
            sm = d["summary"]
            g, prog = sm["median_min_gap_m"], sm["mean_progress_m"]
            g = "n/a" if g is None else f"{g:.2f}"
            prog = "n/a" if prog is None else f"{prog:.2f}"
            lines.append(f"| {_label(n)} | {sm['trials']} | {sm['collisions']} | {g} | {prog} |")
        lines.append("")
    return lines


def _free_section(free: dict) -> list[str]:
    """docs/results.md: the open suite's test split, the intersection with no other car."""
    if not free:
        return []
    first = next(iter(free.values()))

    lines = ["## Free intersections: no other car", "",
             f"The open suite's test split (`racecav suite generate --name {first['suite']}`, common/data/suites/"
             f"{first['suite']}.toml, docs/world.md): the intersection with no other car, {len(first['scenarios'])} "
             f"files, {first['trials_per_scenario']} trials each (trial i: seed {first['base_seed']} + i). Success: "
             "through the crossing along the ego's own road within the file's 4-5 s, no contact. A car that "
             "drives straight at full throttle passes it; what it measures is whether a controller keeps to its "
             "road where nothing needs an evasion (an evasion learnt as a habit of the intersection shows here).",
             "", "| controller | success | collisions | mean progress (m) |", "|---|---:|---:|---:|"]
    for n, d in free.items():
        sm = d["summary"]
        prog = "n/a" if sm["mean_progress_m"] is None else f"{sm['mean_progress_m']:.2f}"
        lines.append(f"| {_label(n)} | {_rate_text(sm)} | {sm['collisions']} | {prog} |")
    return lines + [""]


def _safety_section(results: dict, names: list[str], trials: int, suite: dict, free: dict | None = None) -> list[str]:
    """docs/results.md: every cell run without and with the supervisor (``--safety both``)."""
    free = free or {}
    pairs = [n for n in names if any((n + "+safety", sc) in results for sc in (*SCENARIOS, *CONFLICT))
             or n + "+safety" in suite or n + "+safety" in free]
    if not pairs:
        return []
    cols = [sc for sc in (*SCENARIOS, *CONFLICT) if any((n, sc) in results for n in pairs)]
    head = [SHORT[sc] if sc in SCENARIOS else f"{SHORT[sc.removeprefix('conflict-')]} conflict" for sc in cols]
    lines = ["## Emergency-brake supervisor on/off", "",
             "Each cell run without and with `racecav safety` (per-ray iTTC with the lidar-to-bumper offset, "
             "2-scan debounce, 0.4 s threshold, swept-path gate; its brake is an input of the sim's mux above "
             "the controller, services/safety, docs/controllers.md), on the same seeds: success % off -> on "
             "(collisions off -> on). Its scan -> brake latency and its false brakes over 100 laps of the "
             "empty racetrack and figure eight are `racecav bench safety` (docs/benchmarks.md, section safety).",
             "", "| controller | " + " | ".join(head) + (" | suite (test split) |" if suite else " |")
             + (" free (test split) |" if free else ""),
             "|---|" + "---:|" * (len(cols) + (1 if suite else 0) + (1 if free else 0))]

    def whole(off, on) -> str:
        if not off or not on:
            return "not run"
        a, b = off["summary"], on["summary"]
        return (f"{100 * a['success_rate']:.0f} -> **{100 * b['success_rate']:.0f}** "
                f"({a['collisions']} -> {b['collisions']})")

    def cell(off, on) -> str:
        if off is None or on is None or not off.summary.trials or not on.summary.trials:
            return "not run"
        a, b = off.summary, on.summary
        return (f"{100 * a.success_rate:.0f} -> **{100 * b.success_rate:.0f}** "
                f"({a.collisions} -> {b.collisions})")

    for n in pairs:
        row = [cell(results.get((n, sc)), results.get((n + "+safety", sc))) for sc in cols]
        for d in (x for x in (suite, free) if x):
            row.append(whole(d.get(n), d.get(n + "+safety")))
        lines.append(f"| {_label(n)} | " + " | ".join(row) + " |")
    lines += ["", f"{trials} trials per scenario cell; the suites: their test splits as in the sections above.", ""]
    return lines
