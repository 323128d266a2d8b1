"""racecav train robust-select: bad input named before any trial runs; cells already in its CSV
are kept (an interrupted run resumes) and the table pools them (conflict-timed over the three
scenarios, with Wilson intervals). Its evaluations are `racecav eval` runs, tested elsewhere."""

from __future__ import annotations

import csv
import subprocess

from racecav.common import procs
from racecav.training.robust_select import CONFLICT, FIELDS, PAPER


def _run(*args):
    return subprocess.run(procs.racecav_cmd("train", "robust-select", *args), capture_output=True, text=True,
                          timeout=120)


def test_bad_models_and_perturbations_are_named(tmp_path):
    r = _run("--models", f"a={tmp_path / 'missing.npz'}", "--out", str(tmp_path / "c.csv"))
    assert r.returncode == 2 and "a: no policy file" in r.stdout
    r = _run("--models", "avoid=common/data/policies/avoid.npz", "--perturbations", "s2-nominal,wet-floor",
             "--out", str(tmp_path / "c.csv"))
    assert r.returncode == 2 and "unknown preset 'wet-floor'" in r.stdout
    assert not (tmp_path / "c.csv").exists()


def test_cells_in_the_csv_are_kept_and_pooled(tmp_path):
    out, md = tmp_path / "cells.csv", tmp_path / "t.md"
    rows = [{"model": m, "perturbation": p, "scenario": s, "successes": k, "trials": 10}
            for m, k in (("a", 10), ("b", 5)) for p in ("nominal", "s2-nominal") for s in CONFLICT]
    rows += [{"model": m, "perturbation": "nominal", "scenario": s, "successes": 9, "trials": 10}
             for m in ("a", "b") for s in PAPER]
    with out.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(rows)
    r = _run("--models", "a=common/data/policies/avoid.npz,b=common/data/policies/reversed.npz",
             "--perturbations", "s2-nominal", "--trials", "10", "--out", str(out), "--md", str(md), "--no-references")
    assert r.returncode == 0, r.stdout + r.stderr
    lines = md.read_text().splitlines()
    a = next(ln for ln in lines if ln.startswith("| a |"))
    b = next(ln for ln in lines if ln.startswith("| b |"))
    assert a.count("**100** [89, 100]") == 2 and a.count("**90** [60, 98]") == 3, a
    assert b.count("**50** [33, 67]") == 2, b
    with out.open() as f:
        assert len(list(csv.DictReader(f))) == len(rows)  # nothing re-run, nothing lost
