"""The robustness section of ``racecav eval --table`` (``--sections ...,robust``).

Each controller of ``--robust-controllers`` runs the conflict-timed scenarios under every
perturbation of :func:`perturbations`: the ideal world, the presets of
common/data/perturbations.toml, and the points of three sweeps (added latency, range noise,
friction), ``--robust-trials`` seeded trials per cell, the scenarios' own seeds (the same trials
as the conflict section's first ones). One harness per (controller, perturbation): the sim runs
with ``sim.perturb``. Cells go to the store (ROW.robust.json.gz, cell SCENARIO@PERTURBATION,
their run key carrying the perturbation: evaluation/harness.perturbed), so ``--resume`` and
``--from-store`` work as for the other sections. The document gets the success per controller and
perturbation (pooled over the three scenarios, and per scenario), where each controller breaks
(more than BREAK_POINTS below its own success in the ideal world) and the degradation plots.
"""

from __future__ import annotations

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


def run(args, cfg, store, out: Path, from_store: bool):
    """Every cell of the section, from the store (``--resume``) or measured.

    :returns: ({(controller, perturbation text, scenario): RunResult}, error or None, lacking
        cells (``--from-store``: the cells the store does not hold)).
    """
    from racecav.common.scenario import SCENARIOS_DIR, load_scenario
    from racecav.evaluation.harness import CONTROLLERS, Harness, HarnessError, perturbed
    from racecav.evaluation.trials import NoBar, cell_key, run_trials

    trials = args.robust_trials
    scen = list(registry.CONFLICT_SCENARIOS)
    seeds = {s: (args.seed if args.seed is not None else load_scenario(s).seed) for s in scen}
    results, lacking, error = {}, [], None
    todo = []  # (controller, perturbation) pairs with a cell to measure
    for name in controllers(args):
        for _, p in perturbations():
            ctrl = perturbed(CONTROLLERS[name], p)
            missing_here = False
            for sc in scen:
                key = cell_key(ctrl, False, args.mode, SCENARIOS_DIR / f"{sc}.toml", seeds[sc])
                hit = store.get(name, "robust", cell_name(sc, p), key, trials) if args.resume else None
                if hit is not None:
                    results[(name, p.text(), sc)] = hit
                else:
                    missing_here = True
                    lacking.append(f"{name} {cell_name(sc, p)}")
            if missing_here:
                todo.append((name, p))
    if from_store or not todo:
        return results, None, lacking
    from tqdm import tqdm

    total = len(todo) * len(scen) * trials
    bar = NoBar() if args.no_progress else tqdm(total=total, unit="trial", desc="robust", dynamic_ncols=True,
                                                 mininterval=1.0)
    try:
        for name, p in todo:
            ctrl = perturbed(CONTROLLERS[name], p)
            bar.set_description_str(ctrl.name)
            stem = f"{name}-{p.text()}"
            with Harness(cfg, ctrl, args.mode, scen[0], out / "robust" / "logs" / stem, args.real_time_factor,
                         perturb=p) as h:
                for sc in scen:
                    res, error = run_trials(h, sc, SCENARIOS_DIR / f"{sc}.toml", trials, seeds[sc],
                                            out / "robust" / f"{stem}-{sc}.jsonl", args.resume, bar=bar,
                                            keep_trajectory=False,
                                            store=(store, name, "robust", cell_name(sc, p)))
                    results[(name, p.text(), sc)] = res
                    if error is not None:
                        raise error
    except (HarnessError, Exception, KeyboardInterrupt) as e:
        error = e
    finally:
        bar.close()
    return results, error, []


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


def section(results: dict, args, img: Path, doc: Path, label) -> list[str]:
    """The document's robustness section; ``label(controller)`` is the table's row label."""
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
             f"{3 * trials} pooled trials a difference of {BREAK_POINTS:g} points is well inside it, so a "
             "single \"break\" below is a flag to measure again with more trials, not a verdict. The trivial "
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
        lines.append(f"- {label(n)} (ideal world {base:.0f} %): "
                     + (f"breaks under {', '.join(broken)}" if broken else "breaks under none")
                     + f"; first sweep point that breaks it: {'; '.join(first)}.")
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
              f"--trials {trials} --perturb s2-nominal`.", ""]
    return lines
