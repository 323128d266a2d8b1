"""The robustness section of ``racecav eval --table`` (evaluation/robust.py): its columns and
its cells, keyed by the perturbation (the cells themselves: docs/results.md's store check)."""

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
    r = subprocess.run(procs.racecav_cmd("eval", "--table", "--sections", "robust", "--robust-controllers", "scripted",
                                         "--robust-trials", "2", "--from-store", "--store", str(tmp_path / "store"),
                                         "--doc", str(tmp_path / "r.md"), "--out-dir", str(tmp_path), "--no-progress"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "robust cell" in r.stderr and "scripted conflict-right-to-left@nominal" in r.stderr, \
        r.stdout + r.stderr
