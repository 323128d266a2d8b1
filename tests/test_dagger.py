"""``racecav train dagger`` (training/dagger.py) with the yield teacher (training/teacher.py).

- the imitation loss ignores differences the actuation clips away;
- a dagger run writes a PPO run folder that resumes and that the selection loads.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from racecav.training.dagger import action_bounds, imitation_loss
from tests.checkpoints_support import ROW16


def test_imitation_loss_ignores_what_the_actuation_clips():
    from racecav.common.vehicle import load_car

    lo, hi = (torch.as_tensor(b) for b in action_bounds(load_car("slash")))
    scale = torch.ones(2)
    label = torch.stack([hi, lo])  # full throttle + full left; coast + full right
    beyond = torch.stack([hi + 0.7, lo - 0.4])
    assert float(imitation_loss(beyond, label, lo, hi, scale)) == 0.0
    short = torch.stack([hi - 0.1, lo + 0.1])
    assert abs(float(imitation_loss(short, label, lo, hi, scale)) - 0.01) < 1e-6
    mid = torch.tensor([[0.5, 0.0]])
    assert abs(float(imitation_loss(mid + 0.2, mid, lo, hi, scale)) - 0.04) < 1e-6
    # with a brake (a_T < brake_below brakes) the throttle's bound is the action space's -1: a brake
    # label keeps its value and a coasting prediction is charged for it (it would coast, not brake)
    from racecav.common.vehicle import brake_from_action

    car = load_car("slash")
    blo, bhi = action_bounds(car, brake_below=-0.5)
    assert blo[0] == -1.0 and bhi[0] == 1.0 and blo[1] == lo[1]
    brake = torch.tensor([[float(np.clip(-1.0, blo[0], bhi[0])), 0.0]])
    assert brake_from_action(float(brake[0, 0]), -0.5)
    blo_t, bhi_t = torch.as_tensor(blo), torch.as_tensor(bhi)
    assert float(imitation_loss(torch.tensor([[0.0, 0.0]]), brake, blo_t, bhi_t, scale)) == pytest.approx(0.5)
    assert float(imitation_loss(torch.tensor([[-1.3, 0.0]]), brake, blo_t, bhi_t, scale)) == 0.0


def test_dagger_run_resumes_and_the_selection_loads_its_checkpoints(tmp_path, capsys):
    from racecav.cli import main
    from racecav.training.policy_io import policy_from_checkpoint

    run = tmp_path / "run"
    base = ["train", "dagger", "--run-dir", str(run), "--no-progress"]
    flags = ["--preset", "fast", "--n-envs", "8", "--n-steps", "8", "--checkpoint-every", "64",
             "--grad-steps", "3", "--batch-size", "32", "--world", "figure8", "--heading", "reversed",
             "--n-obstacles", "4", "--driver", "centerline", "--scenarios", "common/data/scenarios/conflict-head-to-head.toml",
             "--scenario-share", "0.5", "--obs-stack", "2", "--lidar", "wide",
             "--init-from", ROW16, "--brake-below", "-0.5", "--mirror-families", "conflict-head-to-head"]
    assert main(base + flags + ["--steps", "128"]) == 0  # in-process: the torch import is paid once
    assert json.loads((run / "latest.json").read_text())["timesteps"] == 128
    assert main(base + ["--resume", "--steps", "192"]) == 0
    rows = list(csv.DictReader((run / "progress.csv").open()))
    assert [int(r["timesteps"]) for r in rows] == [64, 128, 192]
    # the resumed run goes on with the aggregate it had gathered (it restarted empty: 64)
    assert [int(r["dataset"]) for r in rows] == [64, 128, 192]
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["stage"] == "dagger" and cfg["expert"] == "yield"
    pol = policy_from_checkpoint(run / "checkpoints" / "step_000000192.zip", obs_stack=2, lidar="wide")
    a = pol(np.full((1, 2 * 169), 5.0, np.float32))
    assert a.shape == (1, 2) and np.isfinite(a).all()
    # no --init-from: a clear refusal, no run folder
    assert main(["train", "dagger", "--run-dir", str(tmp_path / "x"), "--preset", "fast", "--steps", "64"]) == 2
    assert "--init-from" in capsys.readouterr().out
    assert not (tmp_path / "x" / "config.json").exists()


def test_dagger_with_yield_and_balance_counts_its_steering_round_a_car(tmp_path):
    """`racecav train dagger --expert yield --bc-balance`: the kind that gets half of each minibatch
    (progress.csv's manoeuvres) is the teacher's steering round a car, a share of its labels, not
    every relabelled step (on the head-to-head file every step is relabelled)."""
    import csv

    from racecav.cli import main

    run = tmp_path / "run"
    flags = ["train", "dagger", "--run-dir", str(run), "--no-progress", "--preset", "fast", "--n-envs", "8",
             "--n-steps", "8", "--checkpoint-every", "1000", "--grad-steps", "2", "--batch-size", "32",
             "--world", "figure8", "--heading", "reversed", "--n-obstacles", "4", "--driver", "centerline",
             "--scenarios", "common/data/scenarios/conflict-head-to-head.toml", "--scenario-share", "1.0",
             "--obs-stack", "2", "--lidar", "wide", "--brake-below", "-0.5", "--init-from", ROW16,
             "--expert", "yield", "--mirror-families", "conflict-head-to-head", "--expert-share", "1.0",
             "--bc-balance", "--steps", "384"]
    assert main(flags) == 0
    assert json.loads((run / "config.json").read_text())["bc_balance"] is True
    last = list(csv.DictReader((run / "progress.csv").open()))[-1]
    assert 0.0 < float(last["manoeuvres"]) < 0.5, last


def test_a_balanced_imitation_minibatch_is_half_teacher_labels():
    """--bc-balance: each minibatch half relabelled steps, half the others, however few of either
    are stored; uniform without it, and while one kind is missing."""
    import numpy as np

    from racecav.training.dagger import minibatches

    rng = np.random.default_rng(0)
    man = np.zeros(10_000, bool)
    man[:300] = True  # 3 % relabelled, like yield's brakes among the anchors
    batches = list(minibatches(rng, man, 2048, True, 3))
    assert len(batches) == 3 and all(len(j) == 2048 and man[j].sum() == 1024 for j in batches)
    assert 0.01 < man[next(minibatches(rng, man, 2048, False, 1))].mean() < 0.06
    assert len(next(minibatches(rng, np.zeros(50, bool), 64, True, 1))) == 64  # no relabelled step yet
