"""The robustness section of ``racecav eval --table`` (evaluation/robust.py): its columns and
its cells, keyed by the perturbation (the cells themselves: docs/results.md's store check)."""

import argparse
import subprocess

from racecav.common import procs
from racecav.common.perturb import load_presets
from racecav.evaluation import robust


def test_columns_are_every_preset_and_sweep_point_once():
    cols = robust.perturbations()
    texts = [p.text() for _, p in cols]
    assert len(texts) == len(set(texts)) and texts[0] == "nominal"
    labels = [lb for lb, _ in cols]
    assert set(robust.PRESETS) <= set(labels) <= set(load_presets()) | {"nominal"} | {
        f"{f}={v:g}" for f, _, pts, _, _ in robust.SWEEPS.values() for v in pts}
    assert "friction=0.523" not in labels  # the slippery-floor preset's own cell


def test_from_store_names_the_robust_cells_it_lacks(tmp_path):
    suite = _open_suite(tmp_path / "open")
    n_cols = len(robust.perturbations())
    for extra, lacking in ((("--robust-suite-trials", "0"), 3 * n_cols),  # the suite part off: as before it
                           (("--suite", str(suite)), 3 * n_cols + 2 * (1 + len(robust.PRESETS)))):
        r = subprocess.run(procs.racecav_cmd("eval", "--table", "--sections", "robust", "--robust-controllers",
                                             "scripted", "--robust-trials", "2", *extra, "--from-store", "--store",
                                             str(tmp_path / "store"), "--doc", str(tmp_path / "r.md"), "--out-dir",
                                             str(tmp_path), "--no-progress"),
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and f"robust cell for {lacking} cells" in r.stderr \
            and "scripted conflict-right-to-left@nominal" in r.stderr, r.stdout + r.stderr


def _open_suite(path):
    """A two-file suite (the open suite's families: quick to draw) standing in for the conflict suite."""
    from racecav.evaluation import suite as S

    S.generate(S.load_families("open"), path, n_test=2, n_train=1, seed=1, progress=False)
    return path


def _args(**kw):
    return argparse.Namespace(**{"robust_trials": 2, "robust_suite_trials": 1, "robust_controllers": "scripted",
                                 "seed": None, "mode": "lockstep", "resume": True, **kw})


def test_the_suite_part_runs_under_the_presets_and_the_scenario_cells_keep_their_keys(tmp_path):
    from racecav.common.config import PerturbConfig
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.evaluation.harness import CONTROLLERS, perturbed
    from racecav.evaluation.store import CellStore
    from racecav.evaluation.suite_eval import suite_cells

    suite = suite_cells(str(_open_suite(tmp_path / "open")), "test")
    store = CellStore(tmp_path / "store")
    rows = robust.plan(_args(), store, tmp_path, suite)
    assert [r.perturb.text() for r in rows] == [p.text() for _, p in robust.perturbations()]
    presets = {PerturbConfig().text()} | {PerturbConfig.model_validate(load_presets()[n]).text() for n in robust.PRESETS}
    for r in rows:
        scen = [c for c in r.cells if c.group == "robust"]
        files = [c for c in r.cells if c.group != "robust"]
        # the conflict-timed cells: as the committed store names and keys them
        assert [c.cell for c in scen] == [robust.cell_name(s, r.perturb) for s in robust.registry.CONFLICT_SCENARIOS]
        ctrl = perturbed(CONTROLLERS["scripted"], r.perturb)
        assert [c.trials for c in scen] == [2, 2, 2]
        assert scen[0].path == SCENARIOS_DIR / "conflict-right-to-left.toml" and scen[0].shipped
        # the suite's files under the ideal world and the presets only, one trial each, seed 0 + i
        assert len(files) == (2 if r.perturb.text() in presets else 0), r.perturb.text()
        for c, f in zip(files, suite[1]):
            assert (c.group, c.cell, c.trials, c.seed, c.shipped) == \
                ("robust-suite-open", f"{f.path.name}@{r.perturb.text()}", 1, 0, False)
        assert all(c.stored is None for c in r.cells)
        # a stored cell of that run key is what --resume takes (the controller's name carries the perturbation)
        if files:
            assert ctrl.name == ("scripted" if r.perturb.text() == "nominal" else f"scripted@{r.perturb.text()}")
    assert all(c.group == "robust" for r in robust.plan(_args(robust_suite_trials=0), store, tmp_path, suite)
               for c in r.cells)


def test_the_section_reports_the_suite_under_each_preset_and_where_it_breaks(tmp_path):
    from types import SimpleNamespace

    from racecav.common.config import PerturbConfig

    suite = ("open", [SimpleNamespace(path=tmp_path / f"f{i}.toml") for i in range(2)])
    slippery = PerturbConfig.model_validate(load_presets()["slippery-floor"]).text()

    def res(ok, n):
        return SimpleNamespace(summary=SimpleNamespace(successes=ok, trials=n, success_rate=ok / n))

    results = {}
    for _, p in robust.perturbations():
        for sc in robust.registry.CONFLICT_SCENARIOS:
            results[("scripted", p.text(), sc)] = res(2, 2)
        for f in suite[1]:
            results[("scripted", p.text(), f.path.name)] = res(0 if p.text() == slippery else 1, 1)
    del results[("scripted", "nominal", "f1.toml")]  # a file not measured: the row says so
    lines = robust.section(results, _args(), tmp_path / "img", tmp_path / "r.md", label=lambda n: n, suite=suite)
    text = "\n".join(lines)
    assert "### Conflict suite `open`, test split, under the presets" in text
    rows = {ln.split(" | ")[0].removeprefix("| "): ln for ln in lines if ln.startswith("| ")}
    assert rows["nominal"].endswith("| not run |")
    assert rows[f"slippery-floor ({slippery})"].startswith("| slippery-floor") and "**0**" in rows[
        f"slippery-floor ({slippery})"]
    assert "suite test split (ideal world not run): breaks under none" in text
    results[("scripted", "nominal", "f1.toml")] = res(1, 1)
    text = "\n".join(robust.section(results, _args(), tmp_path / "img", tmp_path / "r.md", label=lambda n: n,
                                    suite=suite))
    assert "suite test split (ideal world 100 %): breaks under slippery-floor." in text
    assert "Conflict suite" not in "\n".join(robust.section(results, _args(robust_suite_trials=0), tmp_path / "img",
                                                            tmp_path / "r.md", label=lambda n: n, suite=suite))
