"""The robustness section of ``racecav eval --table`` (``--sections ...,robust``).

Each controller of ``--robust-controllers`` runs the conflict-timed scenarios under every
perturbation of :func:`perturbations`: the ideal world, the presets of
common/data/perturbations.toml, and the points of three sweeps (added latency, range noise,
friction), ``--robust-trials`` seeded trials per cell, the scenarios' own seeds (the same trials
as the conflict section's first ones). Under the ideal world and each preset it also runs the
conflict suite's test split (the suite section's files), ``--robust-suite-trials`` trials per file
(0: not). One harness per (controller, perturbation), a :class:`Row`: the sim runs with
``sim.perturb``. Cells go to the store (ROW.robust.json.gz, cell SCENARIO@PERTURBATION;
ROW.robust-suite-NAME.json.gz, cell FILE@PERTURBATION; their run key carrying the perturbation:
evaluation/harness.perturbed), so ``--resume`` and ``--from-store`` work as for the other sections;
``--jobs`` and ``--ray`` measure the rows through the table's own dispatch (table.py). The document
gets the success per controller and perturbation (pooled over the three scenarios, and per
scenario), the suite's under the presets, where each controller breaks (more than BREAK_POINTS
below its own success in the ideal world) and the degradation plots (the conflict-timed scenarios).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from racecav.common import registry
from racecav.common.config import PerturbConfig

PRESETS = ("s2-nominal", "s2-pessimistic", "worn-car", "slippery-floor", "late-computer")
SWEEPS = {  # name -> (field, ideal value, points, x label, x scale)
    "latency": ("latency_s", 0.0, (0.05, 0.1, 0.15), "added latency scan -> command (ms)", 1000.0),
    "noise": ("range_noise_m", 0.0, (0.01, 0.02, 0.05), "range noise std (m)", 1.0),
    "friction": ("friction", 1.0, (0.75, 0.523), "floor friction coefficient", 1.0),
}
BREAK_POINTS = 5.0
"""A controller "breaks" under a perturbation where its pooled success is more than this many
points below its own in the ideal world (the issue's target for avoid)."""
DEFAULT_CONTROLLERS = "drl-avoid,drl-reversed,mpc-apf"


def perturbations() -> list[tuple[str, PerturbConfig]]:
    """(label, perturbation) of the section's columns, each perturbation once (a sweep point equal
    to a preset is the preset's cell)."""
    from racecav.common.perturb import load_presets

    presets = load_presets()
    out = [("nominal", PerturbConfig())] + [(n, PerturbConfig.model_validate(presets[n])) for n in PRESETS]
    for field, _, points, _, _ in SWEEPS.values():
        out += [(f"{field}={v:g}", PerturbConfig.model_validate({field: v})) for v in points]
    seen, uniq = set(), []
    for label, p in out:
        if p.text() not in seen:
            seen.add(p.text())
            uniq.append((label, p))
    return uniq


def _label_of(text: str) -> str:
    return next((lb for lb, p in perturbations() if p.text() == text), text)


def controllers(args) -> list[str]:
    return [c.strip() for c in (getattr(args, "robust_controllers", None) or DEFAULT_CONTROLLERS).split(",") if c.strip()]


def cell_name(scenario: str, p: PerturbConfig) -> str:
    return f"{scenario}@{p.text()}"


@dataclass(frozen=True)
class Cell:
    """One cell of the section: a conflict-timed scenario or a suite test file, under one perturbation."""

    group: str
    """Its store group: "robust" (the conflict-timed scenarios) or "robust-suite-NAME"."""
    cell: str
    """Its name in the store: SCENARIO@PERTURBATION or FILE@PERTURBATION."""
    what: str
    """The scenario's name or the suite file's name (the results' third key)."""
    ref: str
    """What the sim loads: a shipped scenario's name or a file's absolute path."""
    path: Path
    seed: int
    trials: int
    jsonl: Path
    """Its resumable per-trial records under --out-dir."""
    stored: object = None
    """The committed complete cell (RunResult) when --resume may use it, else None."""

    @property
    def shipped(self) -> bool:
        """A shipped scenario (installed on every node), not a suite file (it travels with a Ray task)."""
        return self.group == "robust"


@dataclass
class Row:
    """What one harness runs: a controller under one perturbation, over its cells."""

    name: str
    perturb: PerturbConfig
    cells: list = field(default_factory=list)

    @property
    def todo(self) -> list[Cell]:
        return [c for c in self.cells if c.stored is None]


def suite_trials(args) -> int:
    """``--robust-suite-trials``: trials per suite test file under each preset (0: no suite part)."""
    return getattr(args, "robust_suite_trials", 0) or 0


def plan(args, store, out: Path, suite: tuple[str, list] | None = None) -> list[Row]:
    """Every row of the section with what the store holds of its cells (``--resume``).

    :param suite: (suite name, test cells) of the suite part (table.suite_split), None without it:
        the presets and the ideal world then also run every file of the split."""
    from racecav.common.scenario import SCENARIOS_DIR, load_scenario
    from racecav.evaluation.harness import CONTROLLERS, perturbed
    from racecav.evaluation.trials import cell_key

    trials, k = args.robust_trials, suite_trials(args)
    seeds = {s: (args.seed if args.seed is not None else load_scenario(s).seed) for s in registry.CONFLICT_SCENARIOS}
    on_suite = {p.text() for lb, p in perturbations() if lb == "nominal" or lb in PRESETS}
    rows = []
    for name in controllers(args):
        for _, p in perturbations():
            ctrl = perturbed(CONTROLLERS[name], p)

            def cell(group, what, ref, path, seed, n, jsonl):
                key = cell_key(ctrl, False, args.mode, path, seed)
                hit = store.get(name, group, f"{what}@{p.text()}", key, n) if args.resume else None
                return Cell(group, f"{what}@{p.text()}", what, ref, path, seed, n, jsonl, hit)

            stem = f"{name}-{p.text()}"
            cells = [cell("robust", sc, sc, SCENARIOS_DIR / f"{sc}.toml", seeds[sc], trials,
                          out / "robust" / f"{stem}-{sc}.jsonl") for sc in registry.CONFLICT_SCENARIOS]
            if suite is not None and k > 0 and p.text() in on_suite:
                suite_name, files = suite
                folder = out / "robust" / f"suite-{suite_name}" / stem
                cells += [cell(f"robust-suite-{suite_name}", c.path.name, str(c.path.resolve()), c.path.resolve(),
                               args.seed or 0, k, folder / f"{c.path.stem}.jsonl") for c in files]
            rows.append(Row(name, p, cells))
    return rows


def run(args, cfg, store, out: Path, from_store: bool, suite: tuple[str, list] | None = None):
    """Every cell of the section, from the store (``--resume``) or measured here (:func:`run_rows`;
    ``--jobs`` and ``--ray`` measure them before, through table.py's dispatch).

    :returns: ({(controller, perturbation text, scenario or suite file): RunResult}, error or None,
        lacking cells (``--from-store``: the cells the store does not hold)).
    """
    rows = plan(args, store, out, suite)
    results = {(r.name, r.perturb.text(), c.what): c.stored for r in rows for c in r.cells if c.stored is not None}
    lacking = [f"{r.name} {c.cell}" for r in rows for c in r.todo]
    todo = [r for r in rows if r.todo]
    if from_store or not todo:
        return results, None, lacking
    got, error = run_rows(args, cfg, store, out, todo)
    return {**results, **got}, error, []


def run_rows(args, cfg, store, out: Path, rows: list[Row]):
    """Measure the rows' unstored cells in this process, one harness per row; complete cells go to
    the store. Returns ({(controller, perturbation text, scenario or file): RunResult}, error or None)."""
    from tqdm import tqdm

    from racecav.evaluation.harness import CONTROLLERS, Harness, HarnessError, perturbed
    from racecav.evaluation.trials import NoBar, run_trials

    results, error = {}, None
    total = sum(c.trials for r in rows for c in r.todo)
    bar = NoBar() if args.no_progress else tqdm(total=total, unit="trial", desc="robust", dynamic_ncols=True,
                                                 mininterval=1.0)
    try:
        for r in rows:
            ctrl = perturbed(CONTROLLERS[r.name], r.perturb)
            bar.set_description_str(ctrl.name)
            with Harness(cfg, ctrl, args.mode, r.cells[0].ref, out / "robust" / "logs" / f"{r.name}-{r.perturb.text()}",
                         args.real_time_factor, perturb=r.perturb) as h:
                for c in r.todo:
                    res, error = run_trials(h, c.ref, c.path, c.trials, c.seed, c.jsonl, args.resume, bar=bar,
                                            keep_trajectory=False, store=(store, r.name, c.group, c.cell))
                    results[(r.name, r.perturb.text(), c.what)] = res
                    if error is not None:
                        raise error
    except (HarnessError, Exception, KeyboardInterrupt) as e:
        error = e
    finally:
        bar.close()
    return results, error


def _pct_interval(n: int) -> str:
    """The 95 % Wilson interval of a 95 % success over n trials, as the document prints one."""
    from racecav.evaluation.results import wilson

    lo, hi = wilson(round(0.95 * n), n)
    return f"[{100 * lo:.0f}, {100 * hi:.0f}]"


def _pooled(results: dict, name: str, text: str):
    """(successes, trials) over the three scenarios, or None if a cell is absent."""
    cells = [results.get((name, text, sc)) for sc in registry.CONFLICT_SCENARIOS]
    if any(c is None for c in cells):
        return None
    return sum(c.summary.successes for c in cells), sum(c.summary.trials for c in cells)


def _pct(pooled) -> str:
    from racecav.evaluation.results import wilson

    if pooled is None or not pooled[1]:
        return "not run"
    ok, n = pooled
    lo, hi = wilson(ok, n)
    return f"**{100 * ok / n:.0f}** [{100 * lo:.0f}, {100 * hi:.0f}]"


def _rate(pooled) -> float | None:
    return None if pooled is None or not pooled[1] else 100.0 * pooled[0] / pooled[1]


def _suite_pooled(results: dict, name: str, text: str, files: list[str]):
    """(successes, trials) over the suite part's files, or None if a file's cell is absent."""
    cells = [results.get((name, text, f)) for f in files]
    if not files or any(c is None for c in cells):
        return None
    return sum(c.summary.successes for c in cells), sum(c.summary.trials for c in cells)


def section(results: dict, args, img: Path, doc: Path, label, suite: tuple[str, list] | None = None) -> list[str]:
    """The document's robustness section; ``label(controller)`` is the table's row label; ``suite``:
    the suite part's (suite name, test cells), None without it."""
    from racecav.evaluation.plots import plot_degradation

    names = controllers(args)
    perts = perturbations()
    trials = args.robust_trials
    lines = ["## Robustness: sim-to-real perturbations", "",
             f"Each controller on the three conflict-timed scenarios, {trials} seeded trials per scenario and "
             "perturbation (the scenarios' own seeds: the first trials of the conflict section), the sim run with "
             "`racecav sim --perturb ...`: lidar noise and dropped returns (filled as the car's sensor service fills "
             "them), mount yaw, scan jitter, added latency and actuator delay (charged in sim time), steering "
             "offset, motor gain, friction, mass. Presets and the source of every number: docs/robustness.md. "
             "Success % pooled over the three scenarios, with its 95 % Wilson interval: at "
             f"{3 * trials} pooled trials a success of 95 % has the interval {_pct_interval(3 * trials)}, so a "
             f"difference of {BREAK_POINTS:g} points (a \"break\" below) is within the interval of one cell: a "
             "single break is a flag to measure again with more trials, not a verdict. The trivial "
             "references on the same seeds are the conflict section's (their outcome does not depend on the "
             "lidar).", "",
             "| perturbation | " + " | ".join(label(n) for n in names) + " |",
             "|---|" + "---:|" * len(names)]
    for lb, p in perts:
        desc = lb if lb == p.text() or lb == "nominal" else f"{lb} ({p.text()})"
        lines.append(f"| {desc} | " + " | ".join(_pct(_pooled(results, n, p.text())) for n in names) + " |")
    lines += ["", "Per scenario (success %):", "",
              "| perturbation | " + " | ".join(f"{label(n)} {registry.SHORT[s.removeprefix('conflict-')]}"
                                               for n in names for s in registry.CONFLICT_SCENARIOS) + " |",
              "|---|" + "---:|" * (len(names) * len(registry.CONFLICT_SCENARIOS))]
    for lb, p in perts:
        cells = []
        for n in names:
            for sc in registry.CONFLICT_SCENARIOS:
                r = results.get((n, p.text(), sc))
                cells.append("n/a" if r is None or not r.summary.trials else f"{100 * r.summary.success_rate:.0f}")
        lines.append(f"| {lb} | " + " | ".join(cells) + " |")
    k = suite_trials(args)
    on_suite = [(lb, p) for lb, p in perts if lb == "nominal" or lb in PRESETS]
    files = [c.path.name for c in suite[1]] if suite is not None and k > 0 else []
    if files:
        lines += ["", f"### Conflict suite `{suite[0]}`, test split, under the presets", "",
                  f"The conflict suite's test split (the suite section's {len(files)} files, its families mixed), "
                  f"{k} seeded trial{'s' if k != 1 else ''} per file (trial i: seed {args.seed or 0} + i, the suite "
                  "section's first ones) under each preset, beside the ideal world: success % pooled over the files, "
                  "95 % Wilson interval.", "",
                  "| perturbation | " + " | ".join(label(n) for n in names) + " |",
                  "|---|" + "---:|" * len(names)]
        for lb, p in on_suite:
            desc = lb if lb == "nominal" else f"{lb} ({p.text()})"
            lines.append(f"| {desc} | " + " | ".join(_pct(_suite_pooled(results, n, p.text(), files))
                                                      for n in names) + " |")
    lines += ["", f"### Where each controller breaks (pooled success more than {BREAK_POINTS:g} points below its own "
              "in the ideal world)", ""]
    for n in names:
        base = _rate(_pooled(results, n, PerturbConfig().text()))
        if base is None:
            lines.append(f"- {label(n)}: not run")
            continue
        broken = [lb for lb, p in perts[1:] if (r := _rate(_pooled(results, n, p.text()))) is not None
                  and r < base - BREAK_POINTS]
        first = []
        for sweep, (field, ideal, points, _, _) in SWEEPS.items():
            hit = next((v for v in points
                        if (r := _rate(_pooled(results, n, PerturbConfig.model_validate({field: v}).text())))
                        is not None and r < base - BREAK_POINTS), None)
            first.append(f"{sweep}: {'not within the sweep' if hit is None else f'{field}={hit:g}'}")
        on_files = ""
        if files:
            sbase = _rate(_suite_pooled(results, n, PerturbConfig().text(), files))
            sbroken = [lb for lb, p in on_suite[1:] if sbase is not None
                       and (r := _rate(_suite_pooled(results, n, p.text(), files))) is not None
                       and r < sbase - BREAK_POINTS]
            on_files = (f"; suite test split (ideal world {'not run' if sbase is None else f'{sbase:.0f} %'}): "
                        + (f"breaks under {', '.join(sbroken)}" if sbroken else "breaks under none"))
        lines.append(f"- {label(n)} (ideal world {base:.0f} %): "
                     + (f"breaks under {', '.join(broken)}" if broken else "breaks under none")
                     + f"; first sweep point that breaks it: {'; '.join(first)}{on_files}.")
    curves = {}
    for sweep, (field, ideal, points, xlabel, scale) in SWEEPS.items():
        xs = [ideal, *points]
        curves[sweep] = (xlabel, {label(n): [(x * scale, _pooled(results, n, PerturbConfig.model_validate(
            {field: x} if x != ideal else {}).text())) for x in xs] for n in names})
    fig = plot_degradation(curves, img / "results-robust.png",
                           title=f"Success under perturbation, conflict-timed scenarios pooled ({3 * trials} trials "
                                 "per point, 95 % CI)")
    lines += ["", f"![degradation]({fig.relative_to(doc.parent)})", "",
              "Reproduce one cell: `racecav eval --scenario conflict-right-to-left --controller drl-avoid "
              f"--trials {trials} --perturb s2-nominal`"
              + (f"; the suite part: `racecav eval --suite {suite[0]} --controller drl-avoid --trials-per-scenario {k} "
                 "--perturb s2-nominal`" if files else "") + ".", ""]
    return lines
