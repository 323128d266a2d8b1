"""Evaluation cells and training seeds on Ray (evaluation/ray_cells.py, training/sweep.py), on a
local Ray of 2 CPUs: the same outcomes as the local pool, no orphaned service when a worker is
killed mid-cell (and the cell is retried), a 2-trial sweep that runs and resumes."""

from __future__ import annotations

import csv
import gzip
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from racecav.common import procs

RAY_ENV = {"RAY_USAGE_STATS_ENABLED": "0"}
pytestmark = pytest.mark.timeout(900)  # a Ray start and whole commands: minutes on a loaded 2-core box


@pytest.fixture(scope="module")
def ray_address():
    """One local Ray (2 CPUs, on loopback) that the commands below join with --ray ADDRESS: a Ray
    start is the slowest part of a small run."""
    import ray

    os.environ.update(RAY_ENV)
    ray.init(address="local", num_cpus=2, include_dashboard=False, object_store_memory=100 * 2**20,
             _node_ip_address="127.0.0.1", log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


def _racecav(*args: str, timeout: float = 400) -> subprocess.CompletedProcess:
    return subprocess.run(procs.racecav_cmd(*args), capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **RAY_ENV})


def _stored(store: Path) -> dict:
    """(row, group, cell) -> [(seed, success, steps, progress)] of a cell store."""
    out = {}
    for f in sorted(store.glob("*.json.gz")):
        row, group = f.name.removesuffix(".json.gz").split(".", 1)
        with gzip.open(f, "rt") as fh:
            for cell, res in json.load(fh).items():
                out[(row, group, cell)] = [(t["seed"], t["success"], t["steps"], t["progress_m"]) for t in res["trials"]]
    return out


def _open_suite(path: Path) -> Path:
    from racecav.evaluation import suite as S

    S.generate(S.load_families("open"), path, n_test=2, n_train=1, seed=1, progress=False)
    return path


def test_a_table_on_ray_gives_the_local_pools_outcomes(tmp_path, ray_address):
    """Lockstep: the cells of a small table (the conflict-timed scenarios, their obstacle timed by
    the ego), run as Ray tasks, end as the same trials as in one local process, in the same store."""
    table = ("eval", "--table", "--controllers", "scripted", "--sections", "conflict", "--trials", "2", "--no-progress")
    runs = {}
    for name, extra in (("ray", ("--ray", ray_address)), ("local", ())):
        r = _racecav(*table, "--out-dir", str(tmp_path / name), "--doc", str(tmp_path / name / "results.md"),
                     "--store", str(tmp_path / name / "store"), *extra)
        assert r.returncode == 0, r.stdout + r.stderr
        assert ("3 cells on" in r.stdout) == (name == "ray"), r.stdout
        runs[name] = _stored(tmp_path / name / "store")
    ray_cells, local = runs["ray"], runs["local"]
    assert sorted(ray_cells) == sorted(local) and len(local) == 3, sorted(local)
    for key in local:
        a, b = ray_cells[key], local[key]
        assert [t[:3] for t in a] == [t[:3] for t in b], key
        assert np.allclose([t[3] for t in a], [t[3] for t in b], atol=1e-3), key
    log = list(csv.DictReader((tmp_path / "ray" / "table" / "logs" / "ray-cells.csv").open()))
    assert len(log) == 3 and all(float(c["start_s"]) > 0 for c in log)
    # the per-trial records are where a local run keeps them, and --resume has nothing left to run
    assert sorted(p.name for p in (tmp_path / "ray" / "table").glob("*.jsonl")) == \
        sorted(p.name for p in (tmp_path / "local" / "table").glob("*.jsonl"))
    r = _racecav(*table, "--out-dir", str(tmp_path / "ray"), "--doc", str(tmp_path / "ray" / "again.md"),
                 "--store", str(tmp_path / "ray" / "store"), "--ray", ray_address, "--resume")
    assert r.returncode == 0 and "cells on" not in r.stdout, r.stdout + r.stderr
    assert _stored(tmp_path / "ray" / "store") == ray_cells


def test_a_perturbed_robust_cell_on_ray_is_the_local_one(tmp_path, ray_address):
    """A cell of the robust section (conflict right-to-left on the worn car: steering offset, motor
    gain, mass) run as a Ray task through the table's dispatch (ray_cells.run_table) and in this
    process (robust.run_rows): the same store row, cell name, run key and trials (a task that
    dropped the perturbation ends its trials elsewhere: the worn car is slower)."""
    import argparse

    from racecav.common.config import PerturbConfig, load_config, load_presets
    from racecav.evaluation import ray_cells, robust
    from racecav.evaluation.store import CellStore

    worn = PerturbConfig.model_validate(load_presets()["worn-car"]).text()
    args = argparse.Namespace(robust_trials=2, robust_suite_trials=0, robust_controllers="scripted", seed=None,
                              mode="lockstep", resume=False, no_progress=True, real_time_factor=1.0, ray=ray_address,
                              ray_cpus=2.0, ray_retries=0, trials=None, trials_per_scenario=5, compute_charge="fixed",
                              config=None)
    got = {}
    for name in ("ray", "local"):
        args.out_dir = tmp_path / name
        store = CellStore(tmp_path / name / "store")
        row = next(r for r in robust.plan(args, store, args.out_dir) if r.perturb.text() == worn)
        row.cells = row.cells[:1]
        if name == "ray":
            assert ray_cells.run_table(args, [], {}, {}, {}, store, 2, 0, [row]) == 0
        else:
            _, error = robust.run_rows(args, load_config(), store, args.out_dir, [row])
            assert error is None
        got[name] = _stored(tmp_path / name / "store")
        with gzip.open(tmp_path / name / "store" / "scripted.robust.json.gz", "rt") as f:
            (cell,) = json.load(f).values()
        got[name + " controller"] = cell["controller"]["name"]
    assert list(got["ray"]) == list(got["local"]) == [("scripted", "robust", f"conflict-right-to-left@{worn}")]
    assert got["ray controller"] == got["local controller"] == f"scripted@{worn}"
    (a,), (b,) = got["ray"].values(), got["local"].values()
    assert [t[:3] for t in a] == [t[:3] for t in b] and len(a) == 2
    assert np.allclose([t[3] for t in a], [t[3] for t in b], atol=1e-3)


def _cell_procs() -> dict[int, str]:
    """pid -> RACECAV_CELL tag of every tagged process on this machine."""
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            env = Path(f"/proc/{d}/environ").read_bytes().split(b"\0")
        except OSError:
            continue
        tag = next((e.split(b"=", 1)[1].decode() for e in env if e.startswith(procs.CELL_ENV.encode() + b"=")), None)
        if tag is not None:
            out[int(d)] = tag
    return out


def _cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_a_worker_killed_mid_cell_leaves_no_service_and_the_cell_is_retried(tmp_path, ray_address):
    """kill -9 of the Ray worker running a cell (here a suite's two files, one cell): its router,
    sim and controller go too, and Ray runs the cell again to completion."""
    suite = _open_suite(tmp_path / "open")
    before = set(_cell_procs())
    driver = subprocess.Popen(procs.racecav_cmd("eval", "--suite", str(suite), "--controller", "scripted",
                                                "--trials-per-scenario", "5", "--trials", "10", "--ray", ray_address,
                                                "--no-progress", "--out-dir", str(tmp_path)),
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env={**os.environ, **RAY_ENV}, start_new_session=True)
    try:
        deadline, victim = time.monotonic() + 240, None
        while victim is None and time.monotonic() < deadline and driver.poll() is None:
            for pid, tag in _cell_procs().items():  # a cell whose controller runs: it is in its trials
                if pid not in before and "scripted" in _cmdline(pid):
                    victim = tag
            time.sleep(0.1)
        assert victim is not None, "no cell started"
        cell = {pid for pid, tag in _cell_procs().items() if tag == victim}
        names = {_cmdline(p)[3] for p in cell if len(_cmdline(p)) > 3}  # python -m racecav.cli NAME
        assert {"router", "sim", "scripted"} <= names, names
        workers = {int(Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[1]) for p in cell} - cell
        assert len(workers) == 1, workers  # the services' parent: the Ray worker running the cell
        os.kill(workers.pop(), signal.SIGKILL)
        t0 = time.monotonic()
        while any(_alive(p) for p in cell) and time.monotonic() - t0 < 20:
            time.sleep(0.1)
        assert not [p for p in cell if _alive(p)], "services of the killed cell still run"
        out, _ = driver.communicate(timeout=300)
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGTERM)
            driver.wait(30)
    assert driver.returncode == 0, out
    doc = json.loads((tmp_path / "suite-open-test" / "scripted.json").read_text())
    assert doc["complete"] and [s["trials"] for s in doc["scenarios"]] == [5, 5]
    log = list(csv.DictReader((tmp_path / "suite-open-test" / "scripted" / "logs" / "ray-cells.csv").open()))
    assert [c["tag"] for c in log] == [victim]  # the killed cell, finished on its retry
    assert not [p for p in _cell_procs() if p not in before and _alive(p)]


def test_reap_stops_a_cells_processes_whoever_their_parent(tmp_path):
    tag = f"test-{os.getpid()}"
    p = subprocess.Popen([sys.executable, "-c", "import subprocess, sys, time; "
                          "subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)']); time.sleep(60)"],
                         env={**os.environ, procs.CELL_ENV: tag}, start_new_session=True)
    deadline = time.monotonic() + 20
    while len(procs.tagged(tag)) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(procs.tagged(tag)) == 2  # the process and its own child
    assert procs.reap(tag) == 2
    p.wait(5)
    assert procs.tagged(tag) == [] or not any(_alive(x) for x in procs.tagged(tag))


def test_bad_ray_set_ups_exit_2_before_any_start(tmp_path):
    r = _racecav("eval", "--scenario", "head-to-head", "--controller", "scripted", "--ray")
    assert r.returncode == 2 and "--ray is for --table and --suite" in r.stderr
    r = _racecav("train", "sweep", "racing", "--out", str(tmp_path), "--train-args=--seed 3")
    assert r.returncode == 2 and "--seed is set by the sweep" in r.stderr
    r = _racecav("train", "sweep", "racing", "--out", str(tmp_path), "--vary", "n-envs=a,b")
    assert r.returncode == 2 and "--n-envs" in r.stderr
    (tmp_path / "seed0").mkdir()  # a trial folder of another sweep: its run would continue with its own flags
    (tmp_path / "seed0" / "trial.json").write_text(json.dumps({"flags": ["--preset", "paper"]}))
    r = _racecav("train", "sweep", "racing", "--out", str(tmp_path), "--seeds", "0", "--train-args=--preset fast")
    assert r.returncode == 2 and "holds a trial made with other flags" in r.stderr
    assert not (tmp_path / "tune").exists()


TINY = "--preset fast --n-envs 4 --n-steps 32 --batch-size 64 --n-epochs 2 --checkpoint-every 128"


def test_a_two_trial_sweep_runs_and_resumes(tmp_path, ray_address):
    """Two seeds of a tiny racing run on Ray Tune; then the same sweep to more steps continues each
    trial from its checkpoint, and the best trial's folder is what train select and ship take."""
    out = tmp_path / "sweep"
    sweep = ("train", "sweep", "racing", "--seeds", "0,1", "--out", str(out), "--ray", ray_address, "--no-progress",
             f"--train-args={TINY}", "--select-args=--no-intersection --episodes 2")
    r = _racecav(*sweep, "--steps", "128")
    assert r.returncode == 0, r.stdout + r.stderr
    rows = list(csv.DictReader((out / "sweep.csv").open()))
    assert [(x["trial"], x["seed"], x["score_column"], x["error"]) for x in rows] == \
        [("seed0", "0", "env_return", ""), ("seed1", "1", "env_return", "")]
    for x in rows:  # the score is select's pick in the trial's own folder
        best = json.loads((Path(x["run_dir"]) / "best.json").read_text())
        assert float(x["score"]) == pytest.approx(float(best["env_return"]))
    r = _racecav(*sweep, "--steps", "256")
    assert r.returncode == 0, r.stdout + r.stderr
    for seed in (0, 1):
        run = out / f"seed{seed}"
        assert sorted(p.name for p in (run / "checkpoints").glob("step_*.zip")) == \
            ["step_000000128.zip", "step_000000256.zip"]
        assert "resumed" in (run / "train.log").read_text()
        assert json.loads((run / "trial.json").read_text())["steps"] == 256
    best = json.loads((out / "best.json").read_text())
    assert (out / "best").resolve() == Path(best["run_dir"]).resolve()
    assert best["score"] == max(float(x["score"]) for x in csv.DictReader((out / "sweep.csv").open()))
    r = _racecav("train", "select", "--run-dir", str(out / "best"), "--no-intersection", "--episodes", "2",
                 "--no-record", "--no-progress")
    assert r.returncode == 0 and best["checkpoint"] in r.stdout, r.stdout + r.stderr
