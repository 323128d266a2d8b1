"""`racecav train select` on an avoidance run (one with --scenarios): per-family suite columns,
kept across invocations (a tiny real PPO run on the fast world; PyBullet trials in-process)."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import pytest

from tests.test_train_resume import TINY


def _eval_rows(run: Path) -> tuple[list[str], list[dict]]:
    with (run / "eval.csv").open() as f:
        r = csv.DictReader(f)
        return list(r.fieldnames or []), list(r)


@pytest.mark.timeout(600)
def test_select_keeps_family_columns(tmp_path, monkeypatch):
    from racecav.cli import main
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training import select

    # the run record goes to a temporary "committed" folder, not the repository's
    monkeypatch.setattr(select, "COMMITTED", tmp_path / "committed")
    scen = tmp_path / "scenarios"
    scen.mkdir()
    for name in ("right-to-left", "conflict-right-to-left"):
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", scen / f"{name}.toml")
    run = tmp_path / "avoid-tiny"
    assert main(["train", "overtake", "--steps", "256", "--run-dir", str(run), *TINY, "--world", "figure8",
                 "--heading", "reversed", "--n-obstacles", "0", "--scenarios", str(scen),
                 "--scenario-share", "1.0"]) == 0
    sel = ["train", "select", "--run-dir", str(run), "--trials", "1", "--episodes", "2", "--suite-episodes", "8",
           "--last", "1"]
    assert main(sel) == 0
    fields, rows = _eval_rows(run)
    fams = [c for c in fields if c.startswith("suite_") and c not in ("suite_success", "suite_episodes")]
    assert fams and rows and all(rows[-1][c] != "" for c in fams), (fields, rows)
    assert 0.0 <= float(rows[-1]["score"]) <= 1.0

    # nothing new to evaluate: the stored row, its family columns included, stays as it was
    assert main(sel) == 0
    fields2, rows2 = _eval_rows(run)
    assert fields2 == fields and rows2 == rows
    assert (tmp_path / "committed" / run.name / "eval.csv").is_file()
