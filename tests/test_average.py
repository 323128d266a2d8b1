"""Checkpoint averaging along a run (``racecav train average``, training/average.py)."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "training/checkpoints/avoid-gsde-flow120"  # row 31 (the avoid shipped from 2026-12-02 to 12-05)
SOURCE = RUN / "checkpoints/step_005005312.zip"


def _fake_run(tmp_path: Path, n: int) -> tuple[Path, list[dict], list]:
    """A run folder of ``n`` checkpoints: row 31's 5 M policy with the k-th parameter set shifted
    by k * delta and its normalisation's mean shifted by k (so every average is known)."""
    from stable_baselines3 import PPO

    from racecav.training.average import _load_norm, _save_norm

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(RUN / "config.json", run / "config.json")
    model = PPO.load(SOURCE, device="cpu")
    base = {k: v.clone() for k, v in model.policy.state_dict().items()}
    delta = {k: torch.randn(v.shape, generator=torch.Generator().manual_seed(3), dtype=v.dtype) * 0.01
             for k, v in base.items()}
    states, means = [], []
    for k in range(n):
        st = {key: base[key] + k * delta[key] for key in base}
        model.policy.load_state_dict(st)
        dst = run / "checkpoints" / f"step_{(k + 1) * 1000:09d}.zip"
        model.save(dst)
        norm = _load_norm(SOURCE.with_suffix(".vecnorm.pkl"))
        norm.obs_rms.mean = norm.obs_rms.mean + k
        _save_norm(norm, dst.with_suffix(".vecnorm.pkl"))
        states.append(st)
        means.append(norm.obs_rms.mean)
    return run, states, means


def test_average_writes_the_window_means_that_select_can_load(tmp_path, monkeypatch):
    from stable_baselines3 import PPO

    from racecav.common.policy import NumpyPolicy, policy_arrays_from_sb3
    from racecav.training.average import average_run
    from racecav.training.dagger import mean_action
    from racecav.training.select import checkpoint_policy

    torch.set_num_threads(1)
    run, states, means = _fake_run(tmp_path, 4)
    out = tmp_path / "avg"
    written = average_run(run, 3, out, progress=False)
    assert [p.name for p in written] == ["step_000003000.zip", "step_000004000.zip"]  # full windows only
    rec = json.loads((out / "averaged.json").read_text())
    assert rec["window"] == 3 and rec["checkpoints"]["4000"] == [2000, 3000, 4000]
    got = PPO.load(written[-1], device="cpu").policy.state_dict()
    for k, v in got.items():  # the mean of checkpoints 2-4: the base shifted by 2 deltas
        torch.testing.assert_close(v, (states[1][k] + states[2][k] + states[3][k]) / 3, atol=1e-6, rtol=1e-5)
    with written[-1].with_suffix(".vecnorm.pkl").open("rb") as f:
        norm = pickle.load(f)
    np.testing.assert_allclose(norm.obs_rms.mean, means[2])  # shifts 1, 2, 3: mean 2
    src_var = pickle.load(SOURCE.with_suffix(".vecnorm.pkl").open("rb")).obs_rms.var
    np.testing.assert_allclose(norm.obs_rms.var, src_var + 2 / 3)  # + the variance of the means
    # select's loader reads the average with the run's settings: the numpy path equals SB3 on it
    pol = checkpoint_policy(written[-1])
    assert pol.obs_stack == 2
    obs = np.random.default_rng(0).normal(size=(16, 338)).astype(np.float32)
    model = PPO.load(written[-1], device="cpu")
    raw = NumpyPolicy(policy_arrays_from_sb3(model), {})
    want = np.clip(mean_action(model.policy, torch.as_tensor(obs)).detach().numpy(), -1, 1)
    np.testing.assert_allclose(np.stack([raw(o) for o in obs]), want, atol=1e-5)
    # select's record of the folder keeps what the averages are (the ablation's change column)
    from racecav.training import select

    monkeypatch.setattr(select, "COMMITTED", tmp_path / "committed")
    assert json.loads((select.save_run_record(out) / "averaged.json").read_text()) == rec
    # a window of one is the run itself
    one = average_run(run, 1, tmp_path / "one", progress=False)
    assert len(one) == 4
    for k, v in PPO.load(one[0], device="cpu").policy.state_dict().items():
        assert torch.equal(v, states[0][k])


def test_average_refuses_bad_input(tmp_path):
    from stable_baselines3 import PPO

    from racecav.training.average import average_run, average_states
    from racecav.training.widen import widen

    run, _states, _means = _fake_run(tmp_path, 2)
    with pytest.raises(ValueError, match="fewer than --window 3"):
        average_run(run, 3, tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match=">= 1"):
        average_run(run, 0, tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match="source run"):
        average_run(run, 1, run, progress=False)
    with pytest.raises(FileNotFoundError, match="config.json"):
        average_run(tmp_path / "nowhere", 1, tmp_path / "a", progress=False)
    state = PPO.load(SOURCE, device="cpu").policy.state_dict()
    with pytest.raises(ValueError, match="architectures"):
        average_states([state, widen(state, 128)])
    # the CLI: a clear message, no traceback
    from racecav.cli import main

    with pytest.raises(SystemExit, match="fewer than --window 5"):
        main(["train", "average", "--run-dir", str(run), "--window", "5", "--out", str(tmp_path / "b"), "--no-progress"])
