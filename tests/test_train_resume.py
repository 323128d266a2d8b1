"""`racecav train ... --resume` continues an interrupted run: same step count, same learning
curve, Adam state and normalisation statistics restored (tiny real PPO runs on the fast world)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# 4 envs x 32 steps = 128 samples per rollout, 2 minibatches of 64, 2 epochs = 4 Adam steps per update
TINY = ["--preset", "fast", "--n-envs", "4", "--n-steps", "32", "--batch-size", "64", "--n-epochs", "2",
        "--checkpoint-every", "256", "--seed", "3", "--no-progress"]
ROLLOUT, ADAM_STEPS_PER_UPDATE = 128, 4


def _args(run_dir: Path, steps: int, *extra: str) -> list[str]:
    return ["train", "racing", "--steps", str(steps), "--run-dir", str(run_dir), *TINY, *extra]


def _train(run_dir: Path, steps: int, *extra: str) -> int:
    """In-process, through the real CLI entry point (saves a process start on a loaded box)."""
    from racecav.cli import main

    return main(_args(run_dir, steps, *extra))


def _curve(run_dir: Path) -> list[int]:
    with (run_dir / "progress.csv").open() as f:
        return [int(float(r["timesteps"])) for r in csv.DictReader(f)]


def _updates_logged(run_dir: Path) -> list[bool]:
    """Per progress.csv row: whether it holds the PPO update's values (train/*)."""
    with (run_dir / "progress.csv").open() as f:
        return [r["approx_kl"] != "" and r["value_loss"] != "" for r in csv.DictReader(f)]


def _adam_steps(zip_path: Path) -> int:
    from stable_baselines3 import PPO

    model = PPO.load(zip_path, device="cpu")
    state = model.policy.optimizer.state_dict()["state"]
    return int(next(iter(state.values()))["step"])


def _obs_count(pkl: Path) -> float:
    import pickle

    with pkl.open("rb") as f:
        return float(pickle.load(f).obs_rms.count)


def test_resume_continues_run(tmp_path):
    run = tmp_path / "run"
    assert _train(run, 512) == 0
    first = json.loads((run / "latest.json").read_text())
    assert first["timesteps"] == 512 and first["final"]
    assert _curve(run) == [128, 256, 384, 512]
    # each row holds the update on its own rollout: the first row has one, the last is not lost
    # (SB3 dumps a rollout's log before its update; training/train._csv_writer waits for it)
    assert _updates_logged(run) == [True] * 4
    assert _adam_steps(run / "latest.zip") == 4 * ADAM_STEPS_PER_UPDATE
    count0 = _obs_count(run / "latest.vecnorm.pkl")

    # a second start without --resume refuses to overwrite the run
    assert _train(run, 1024) == 2

    assert _train(run, 1024, "--resume") == 0
    last = json.loads((run / "latest.json").read_text())
    assert last["timesteps"] == 1024
    assert _curve(run) == list(range(128, 1025, 128))  # one curve, no restart, no duplicates
    assert _updates_logged(run) == [True] * 8
    # Adam continued (a fresh optimizer would count only the 4 updates after the resume)
    assert _adam_steps(run / "latest.zip") == 8 * ADAM_STEPS_PER_UPDATE
    # normalisation statistics continued too
    assert _obs_count(run / "latest.vecnorm.pkl") > count0 + 500
    assert json.loads((run / "config.json").read_text())["seed"] == 3

    # a run resumed from its committed record (training/checkpoints/<run>/: latest.* and the
    # CSVs, no checkpoints/ folder) goes on too, writing its checkpoints into a new folder
    record = tmp_path / "record"
    shutil.copytree(run, record, ignore=shutil.ignore_patterns("checkpoints"))
    assert _train(record, 1152, "--resume") == 0
    assert json.loads((record / "latest.json").read_text())["timesteps"] == 1152
    assert (record / "checkpoints" / "step_000001152.zip").is_file()


@pytest.mark.timeout(600)
def test_sigterm_checkpoints_and_resume_continues(tmp_path):
    run = tmp_path / "run"
    # a real process and a real signal
    proc = subprocess.Popen([sys.executable, "-m", "racecav.cli", *_args(run, 10_000_000)], cwd=ROOT,
                            env=dict(os.environ, OPENBLAS_NUM_THREADS="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 500  # process start is slow on a loaded 2-core box
        while not (run / "latest.json").is_file():  # first periodic checkpoint (256 samples)
            assert proc.poll() is None, proc.stdout.read().decode()
            assert time.monotonic() < deadline
            time.sleep(0.2)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out.decode()
    stopped = json.loads((run / "latest.json").read_text())
    n = stopped["timesteps"]
    assert not stopped["final"] and n >= 256
    assert n % ROLLOUT == 0  # the unfinished rollout is dropped: the count matches the updates
    assert _adam_steps(run / "latest.zip") == n // ROLLOUT * ADAM_STEPS_PER_UPDATE
    assert _curve(run)[-1] <= n + ROLLOUT

    assert _train(run, n + 2 * ROLLOUT, "--resume") == 0
    curve = _curve(run)
    assert curve == sorted(set(curve)) and curve[-1] == n + 2 * ROLLOUT
    assert curve[-2:] == [n + ROLLOUT, n + 2 * ROLLOUT]
    assert _adam_steps(run / "latest.zip") == (n // ROLLOUT + 2) * ADAM_STEPS_PER_UPDATE


def test_init_from_carries_weights_and_normalisation(tmp_path):
    """A new run started from another's checkpoint (--init-from, e.g. a new world) starts from
    its weights and its observation statistics, not from fresh ones; --world is recorded."""
    import numpy as np
    from stable_baselines3 import PPO

    src = tmp_path / "src"
    assert _train(src, 256) == 0
    ck = src / "checkpoints" / "step_000000256.zip"
    dst = tmp_path / "dst"
    assert _train(dst, 128, "--init-from", str(ck), "--world", "figure8") == 0
    assert json.loads((dst / "config.json").read_text())["env"]["world"] == "figure8"
    # statistics carried over: the count keeps growing from the source's 256 samples
    src_count = _obs_count(ck.with_suffix(".vecnorm.pkl"))
    assert src_count >= 256 and _obs_count(dst / "latest.vecnorm.pkl") >= src_count + 128
    # weights carried over: one small update away from the source, far from a fresh init
    a = PPO.load(ck, device="cpu").policy.state_dict()
    b = PPO.load(dst / "latest.zip", device="cpu").policy.state_dict()
    fresh = PPO.load(tmp_path / "src" / "checkpoints" / "step_000000256.zip", device="cpu")
    fresh.policy.apply(lambda m: m.reset_parameters() if hasattr(m, "reset_parameters") else None)
    k = "mlp_extractor.policy_net.0.weight"
    assert np.abs((b[k] - a[k]).numpy()).max() < np.abs((fresh.policy.state_dict()[k] - a[k]).numpy()).max() / 5


def test_a_save_interrupted_leaves_no_truncated_checkpoint(tmp_path):
    """training/runs.save_checkpoint: a run killed while writing its checkpoint leaves no
    step_*.zip (select and --resume read every one), and a finished save leaves no partial file."""
    from racecav.training.runs import save_checkpoint

    class Model:
        num_timesteps = 4096

        def __init__(self, fail):
            self.fail = fail

        def save(self, path):
            Path(path).write_bytes(b"PK\x03\x04 half a zip")
            if self.fail:
                raise KeyboardInterrupt  # the kill, mid-write

    class Norm:
        def save(self, path):
            Path(path).write_bytes(b"moments")

    (tmp_path / "checkpoints").mkdir()
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path, Model(fail=True), Norm(), wall_s=1.0)
    assert not list((tmp_path / "checkpoints").glob("step_*.zip")) and not (tmp_path / "latest.json").exists()
    ck = save_checkpoint(tmp_path, Model(fail=False), Norm(), wall_s=2.0)
    names = sorted(p.name for p in (tmp_path / "checkpoints").iterdir() if not p.name.startswith("partial"))
    assert names == [f"{ck.name}.vecnorm.pkl", f"{ck.name}.zip"]
    assert (tmp_path / "latest.zip").read_bytes() == ck.with_suffix(".zip").read_bytes()
