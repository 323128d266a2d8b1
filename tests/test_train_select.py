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
    from racecav.training import runs, select

    # the run record goes to a temporary "committed" folder, not the repository's
    monkeypatch.setattr(runs, "COMMITTED", tmp_path / "committed")
    monkeypatch.setattr(runs, "IMAGES", tmp_path / "img")
    scen = tmp_path / "scenarios"
    scen.mkdir()
    for name in ("right-to-left", "conflict-right-to-left"):
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", scen / f"{name}.toml")
    run = tmp_path / "avoid-tiny"
    assert main(["train", "overtake", "--steps", "256", "--run-dir", str(run), *TINY, "--world", "figure8",
                 "--heading", "reversed", "--n-obstacles", "0", "--scenarios", str(scen),
                 "--scenario-share", "1.0", "--curriculum", "--curriculum-boost", "right-to-left=2"]) == 0
    from racecav.evaluation import suite as S

    free = tmp_path / "open"  # the free-road column: a generated suite of intersections with no car
    S.generate(S.load_families("open"), free, n_test=1, n_train=4, seed=1, progress=False)
    assert select.free_suite_or_none(str(tmp_path / "not-generated")) is None  # skipped, with a warning
    sel = ["train", "select", "--run-dir", str(run), "--trials", "1", "--episodes", "2", "--suite-episodes", "8",
           "--last", "1", "--free-suite", str(free)]
    assert main(sel) == 0
    fields, rows = _eval_rows(run)
    fams = [c for c in fields if c.startswith("suite_") and c not in ("suite_success", "suite_episodes")]
    assert fams and rows and all(rows[-1][c] != "" for c in fams), (fields, rows)
    assert 0.0 <= float(rows[-1]["score"]) <= 1.0
    # 4 fast-world episodes (half of --suite-episodes) on the free roads
    assert float(rows[-1]["free_success"]) in (0.0, 0.25, 0.5, 0.75, 1.0), rows[-1]

    # nothing new to evaluate: the stored row, its family columns included, stays as it was
    assert main(sel) == 0
    fields2, rows2 = _eval_rows(run)
    assert fields2 == fields and rows2 == rows
    record = tmp_path / "committed" / run.name
    assert (record / "eval.csv").is_file()

    # a row evaluated before the free column: the column alone is added, the rest stays as it was
    with (run / "eval.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fields)
        w.writeheader()
        w.writerows([{**r, "free_success": ""} for r in rows])
    assert main(sel) == 0
    assert _eval_rows(run) == (fields, rows)

    # --no-record: a scratch evaluation leaves the committed records alone
    shutil.rmtree(record)
    assert main(sel + ["--no-record", "--newest-first", "--no-progress"]) == 0
    assert not record.exists()
    assert _eval_rows(run) == (fields, rows)


@pytest.mark.timeout(300)
def test_references_never_evade(tmp_path):
    """`racecav train references`: the non-evading cars on the selection cells. Full throttle wins
    the paper-timed side scenarios by speed and loses head-to-head; 1 m/s loses all three."""
    from racecav.cli import main
    from racecav.common.scenario import SCENARIOS_DIR

    scen = tmp_path / "scenarios"
    scen.mkdir()
    shutil.copy(SCENARIOS_DIR / "conflict-left-to-right.toml", scen / "conflict-left-to-right.toml")
    out = tmp_path / "references.csv"
    assert main(["train", "references", "--trials", "2", "--suite-episodes", "8", "--suite", str(scen),
                 "--out", str(out)]) == 0
    with out.open() as f:
        rows = {r["reference"]: r for r in csv.DictReader(f)}
    slow, fast = rows["straight 1 m/s"], rows["straight, full throttle"]
    assert float(slow["a_throttle"]) < 0.5 and float(fast["a_throttle"]) == 1.0
    paper = ("right-to-left", "head-to-head", "left-to-right")
    assert [float(slow[f"{s}_success"]) for s in paper] == [0.0, 0.0, 0.0]
    assert [float(fast[f"{s}_success"]) for s in paper] == [1.0, 0.0, 1.0]
    for r in (slow, fast):  # a synchronised crossing meets a car that holds its course
        assert float(r["conflict-left-to-right_success"]) == 0.0 and float(r["suite_success"]) == 0.0
        cells = [float(r[k]) for k in ("suite_success", "conflict_success", "intersection_success")]
        assert float(r["score"]) == pytest.approx(sum(cells) / 3)


def test_targets_rank_by_targets_met_and_the_page_names_the_pick(tmp_path):
    """training/targets.py: a checkpoint that misses only the paper-timed left-to-right ranks above
    one with a higher score that misses three, and of two that miss it, the nearer one first; a rate of 89.6 % prints and counts as 90 %;
    the committed records' pick is a committed checkpoint, and the page says whether avoid is it."""
    import json

    from racecav.common.policy import MODELS_DIR
    from racecav.training import targets
    from racecav.training.runs import COMMITTED

    cols = ["timesteps", "checkpoint", "score", "conflict-right-to-left_success", "conflict-head-to-head_success",
            "conflict-left-to-right_success", "suite_success", "suite_episodes", "suite_cross-left", "suite_head-on",
            "right-to-left_success", "head-to-head_success", "left-to-right_success"]
    rows = {"a": [1e6, "step_a.zip", 0.92, 1.0, 0.84, 0.99, 0.91, 512, 0.67, 0.9, 1.0, 0.98, 0.76],
            "b": [4e6, "step_b.zip", 0.91, 0.99, 0.896, 0.98, 0.92, 512, 0.75, 0.9, 1.0, 0.99, 0.51],
            # 7 of 8 like b, missing the same target by fewer points: ranks first despite the lower score
            "c": [2e6, "step_c.zip", 0.90, 0.99, 0.9, 0.98, 0.92, 512, 0.75, 0.9, 1.0, 0.99, 0.60]}
    for run, vals in rows.items():
        (tmp_path / run).mkdir()
        with (tmp_path / run / "eval.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerows([cols, vals])
    top = targets.ranked(targets.evaluated(tmp_path))
    assert [r["run"] for r in top] == ["c", "b", "a"]
    assert [sum(targets.met(r)) for r in top] == [7, 7, 5]
    assert [targets.shortfall(r) for r in top] == [40, 49, 6 + 3 + 24]
    table = targets.markdown(targets.evaluated(tmp_path), targets.references(COMMITTED))
    assert "| b | 4.0 M | 7 / 8 | 49 | 91 | 99 | 90 |" in table and "*51*" in table and "*67*" in table
    # the references close the table: full throttle passes only the paper-timed side scenarios
    assert "| *straight, full throttle* | reference | 2 / 8 |" in table, table

    # the committed records' pick can be shipped from committed files, and the page says whether it is
    pick = targets.ranked(targets.evaluated(COMMITTED))[0]
    assert (COMMITTED / pick["run"] / "checkpoints" / pick["checkpoint"]).is_file(), pick["checkpoint"]
    shipped = json.loads((MODELS_DIR / "avoid.json").read_text())
    text = targets.section(COMMITTED, shipped)
    is_shipped = (pick["run"], pick["checkpoint"]) == (shipped["run"], shipped["checkpoint"])
    assert ("samples, is the shipped avoid." in text) == is_shipped and ("is not shipped yet" in text) != is_shipped


def test_checkpoint_policy_is_the_shipped_policy_exported_from_it(tmp_path):
    """The shipped avoid was exported from the committed checkpoint its metadata names (run and
    checkpoint): read back from the run's .zip with the run's config.json, it has the same view
    settings and the same actions. A checkpoint outside a run folder is an error naming the
    missing record."""
    import json

    import numpy as np

    from racecav.common.policy import MODELS_DIR, load_policy
    from racecav.training.policy_io import checkpoint_policy
    from racecav.training.runs import COMMITTED

    meta = json.loads((MODELS_DIR / "avoid.json").read_text())
    ck = COMMITTED / meta["run"] / "checkpoints" / meta["checkpoint"]
    pol, shipped = checkpoint_policy(ck), load_policy("avoid")
    for k in ("lidar", "obs_stack", "obs_stride", "brake_below"):
        assert pol.metadata.get(k) == shipped.metadata.get(k), k
    obs = np.random.default_rng(0).uniform(0.2, 12.0, (64, shipped.obs_stack * 169)).astype(np.float32)
    assert np.allclose(pol(obs), shipped(obs), atol=1e-5)
    shutil.copy(ck, tmp_path / "step_1.zip")
    with pytest.raises(FileNotFoundError, match="no run record"):
        checkpoint_policy(tmp_path / "step_1.zip")


def test_paths_draws_a_checkpoint_and_refuses_an_unknown_scenario(tmp_path, capsys):
    """`racecav train paths`: the figure and each scenario's success, from a run's checkpoint."""
    from racecav.cli import main

    from tests.checkpoints_support import ROW31

    ckpt = ROW31
    out = tmp_path / "paths.png"
    assert main(["train", "paths", "--policy", ckpt, "--scenarios", "left-to-right,conflict-left-to-right",
                 "--trials", "2", "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000
    assert "left-to-right" in capsys.readouterr().out
    assert main(["train", "paths", "--policy", ckpt, "--scenarios", "nope", "--trials", "1",
                 "--out", str(tmp_path / "x.png")]) == 2
    assert "nope" in capsys.readouterr().out and not (tmp_path / "x.png").exists()


def test_reference_drivers_are_the_registrys_scripted_controllers():
    """The in-process references are the registry's ``scripted`` and ``full-throttle`` controllers:
    the program the harness hands ``racecav scripted`` (printed to 4 decimals), and the throttles
    of training/checkpoints/references.csv."""
    from racecav.evaluation.harness import CONTROLLERS
    from racecav.evaluation.inprocess import reference_drivers
    from racecav.training.runs import REFERENCES_CSV

    drivers = reference_drivers()
    assert len(drivers) == 2
    for drv, name in zip(drivers.values(), ("scripted", "full-throttle")):
        args = CONTROLLERS[name].args
        a_t, a_d, _duration = (float(v) for v in args[args.index("--program") + 1].split(","))
        assert abs(float(drv.action[0]) - a_t) < 1e-4 and float(drv.action[1]) == a_d == 0.0
    with REFERENCES_CSV.open() as f:
        stored = {r["reference"]: float(r["a_throttle"]) for r in csv.DictReader(f)}
    assert stored == {k: float(d.action[0]) for k, d in drivers.items()}
