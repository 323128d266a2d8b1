"""docs/training.md is generated (``racecav train report``) from committed files only: the
ablation's rows (training/ablation.csv), the prose (docs/training_*.md), the run records and the
policies' metadata. And a run record that names a removed experiment is refused by name."""

from __future__ import annotations

import csv
import json

import pytest


def test_training_md_is_what_the_report_writes():
    from racecav.training.report import DOC, render

    assert DOC.read_text() == render(), "docs/training.md is stale: run `racecav train report --reuse`"


def test_ablation_csv_holds_every_row_and_the_shipped_one():
    from racecav.common.policy import MODELS_DIR
    from racecav.training.report import ABLATION_CSV

    with ABLATION_CSV.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) >= 95 and [int(r["row"]) for r in rows] == list(range(1, len(rows) + 1))
    runs = {r["run"]: r for r in rows}
    assert all(r["base"] in runs or r["base"] == "" for r in rows)  # every row names the row it builds on
    shipped = json.loads((MODELS_DIR / "avoid.json").read_text())
    row = runs[shipped["run"]]
    assert row["verdict"] == "shipped (avoid)" and row["best_checkpoint"] == shipped["checkpoint"]
    assert json.loads(row["settings"])["expert"] == "yield"
    assert {r["verdict"] for r in rows} <= {"shipped (avoid)", "shipped (avoid-paper)", "kept", "rejected",
                                            "rejected (never evaluated)"}


def test_a_removed_setting_loads_turned_off_and_is_refused_turned_on(tmp_path):
    from racecav.training.runs import EXPERIMENTS_COMMIT, load_run_config

    cfg = {"stage": "overtake", "bc_coef": 0.0, "mirror_symmetric": False, "expert": "planner",
           "bc_label_steps": 2, "env": {"contact_penalty": 0.0, "lane_keeping_horizon_s": 2.5, "obs_stack": 2}}
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    tc, _ = load_run_config(tmp_path)
    assert tc.env.obs_stack == 2 and tc.expert == "yield"
    for key, value in (("bc_coef", 0.5), ("privileged_critic", True)):
        (tmp_path / "config.json").write_text(json.dumps({**cfg, key: value}))
        with pytest.raises(ValueError, match=f"{key} = .*commit {EXPERIMENTS_COMMIT}"):
            load_run_config(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({**cfg, "env": {"lane_keeping": 2.0}}))
    with pytest.raises(ValueError, match=f"env.lane_keeping = 2.0 .*{EXPERIMENTS_COMMIT}"):
        load_run_config(tmp_path)
    # training under randomised perturbations (row 97): its own commit; a recipe stage's null loads
    (tmp_path / "config.json").write_text(json.dumps({**cfg, "env": {"perturb": None}}))
    assert load_run_config(tmp_path)[0].env.obs_stack == 1
    (tmp_path / "config.json").write_text(json.dumps({**cfg, "env": {"perturb": {"latency_s": 0.1}}}))
    with pytest.raises(ValueError, match=r"env.perturb = .*commit dc49441"):
        load_run_config(tmp_path)
    # the recipe's tried stages (the stand timer, the map curriculum): their commit
    (tmp_path / "config.json").write_text(json.dumps({**cfg, "env": {"stand_input": 3.0}}))
    with pytest.raises(ValueError, match=r"env.stand_input = 3.0 .*commit 814eb57"):
        load_run_config(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({**cfg, "stage": "dagger", "balance_standing": True}))
    with pytest.raises(ValueError, match=r"balance_standing = True .*commit 079c3b6"):
        load_run_config(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({**cfg, "stage": "dagger", "expert": "mirror"}))
    with pytest.raises(ValueError, match=f"expert = 'mirror'.*{EXPERIMENTS_COMMIT}"):
        load_run_config(tmp_path)
