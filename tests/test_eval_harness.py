"""The evaluation harness end to end: real router, sim and controller processes over Zenoh."""

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from racecav.common import procs
from racecav.common.config import load_config
from racecav.evaluation.harness import CONTROLLERS, Controller, Harness, missing
from racecav.evaluation.results import validate_run

# A scenario file of our own (not a shipped one): an obstacle car parked beside the ego's road.
PARKED = """
name = "parked-beside"
world = "intersection"
duration_s = 7.0
[ego]
x = -4.0
y = 0.0
yaw_deg = 0.0
speed = 1.0
[[obstacles]]
x = 0.0
y = 0.8
yaw_deg = 0.0
speed = 0.0
[success]
min_progress_m = 4.0
"""


def _eval(tmp_path, *args, timeout=120):
    return subprocess.run(procs.racecav_cmd("eval", *args, "--out-dir", str(tmp_path), "--no-progress"),
                          capture_output=True, text=True, timeout=timeout)


def test_eval_cli_scripted_head_to_head(tmp_path):
    out = tmp_path / "r.json"
    r = _eval(tmp_path, "--scenario", "head-to-head", "--controller", "scripted", "--trials", "2",
              "--json", str(out), "--plot", str(tmp_path / "r.png"))
    assert r.returncode == 0, r.stdout + r.stderr
    res = validate_run(out)
    assert res.complete and len(res.trials) == 2 and [t.seed for t in res.trials] == [0, 1]
    for t in res.trials:  # the non-evading car meets the head-on obstacle near the crossing
        assert t.collided and not t.success and t.contact_with == "car1"
        assert 3.0 < t.contact_time_s < 5.0 and t.min_gap_m == 0.0
        assert t.steps == len(t.trajectory.t) and len(t.trajectory.obstacles) == 1
        assert t.commands >= t.steps - 1 and t.latency_ms.n == t.commands and t.latency_ms.median > 0
        assert t.latency_clock == "router"  # the router stamps every sample it routes
        ego, obs = np.array(t.trajectory.ego), np.array(t.trajectory.obstacles[0])
        assert ego[-1, 0] > ego[0, 0] + 3 and obs[-1, 0] < obs[0, 0] - 3  # they drove at each other
    assert res.summary.ci95 is not None and res.summary.collisions == 2
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len((tmp_path / "r.jsonl").read_text().splitlines()) == 2
    assert "scan->command latency median" in r.stdout


def test_eval_cli_any_scenario_file_and_success(tmp_path):
    sc = tmp_path / "parked.toml"
    sc.write_text(PARKED)
    r = _eval(tmp_path, "--scenario", str(sc), "--controller", "scripted", "--trials", "1", "--seed", "7")
    assert r.returncode == 0, r.stdout + r.stderr
    res = validate_run(tmp_path / "parked-beside-scripted.json")
    t = res.trials[0]
    assert t.seed == 7 and t.success and not t.collided and t.progress_m >= 4.0
    # driving straight past a car parked 0.8 m to the left: footprints 0.8 - 0.3 apart
    assert t.min_gap_m == pytest.approx(0.5, abs=0.08) and t.min_center_distance_m == pytest.approx(0.8, abs=0.08)


def test_malformed_scenario_file_is_rejected_naming_the_field(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(PARKED.replace("duration_s = 7.0", "duration_s = -1.0"))
    r = _eval(tmp_path, "--scenario", str(bad), "--controller", "scripted", "--trials", "1", timeout=60)
    assert r.returncode == 2 and "duration_s" in r.stderr and str(bad) in r.stderr
    bad.write_text(PARKED.replace("[success]", "[sucess]"))
    r = _eval(tmp_path, "--scenario", str(bad), "--controller", "scripted", "--trials", "1", timeout=60)
    assert r.returncode == 2 and "sucess" in r.stderr
    bad.write_text("name = [unclosed")
    r = _eval(tmp_path, "--scenario", str(bad), "--controller", "scripted", "--trials", "1", timeout=60)
    assert r.returncode == 2 and "invalid TOML" in r.stderr
    assert not (tmp_path / "logs").exists()  # refused before any process started


def test_interrupted_eval_is_partial_and_resumes(tmp_path):
    out = tmp_path / "r.json"
    jsonl = tmp_path / "r.jsonl"
    args = ["--scenario", "right-to-left", "--controller", "scripted", "--json", str(out)]
    p = subprocess.Popen(procs.racecav_cmd("eval", *args, "--trials", "200", "--out-dir", str(tmp_path),
                                           "--no-progress"),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 90
    while not (jsonl.exists() and len(jsonl.read_text().splitlines()) >= 2):
        assert p.poll() is None and time.monotonic() < deadline, p.communicate()
        time.sleep(0.1)
    os.kill(p.pid, signal.SIGTERM)
    stdout, stderr = p.communicate(timeout=60)
    assert p.returncode == 130, stdout + stderr
    assert "PARTIAL" in stderr
    res = validate_run(out)
    done = len(res.trials)
    assert not res.complete and res.stopped_reason.startswith("interrupted") and 2 <= done < 200
    assert res.trials_requested == 200 and res.summary.trials == done
    first = jsonl.read_text().splitlines()[:done]
    # resume: only the missing trials run, the finished ones are kept as they were
    r = _eval(tmp_path, *args, "--trials", str(done + 1), "--resume")
    assert r.returncode == 0, r.stdout + r.stderr
    res2 = validate_run(out)
    assert res2.complete and [t.index for t in res2.trials] == list(range(done + 1))
    lines = jsonl.read_text().splitlines()
    assert lines[:done] == first and len(lines) == done + 1
    # a JSONL of another run (different seed) is refused, not mixed in
    r = _eval(tmp_path, *args, "--trials", str(done + 2), "--resume", "--seed", "5")
    assert r.returncode == 2 and "belongs to run" in r.stderr


def _random_policy(path: Path) -> Path:
    rng = np.random.default_rng(0)
    arrays = dict(w0=rng.normal(0, 0.1, (170, 64)), b0=np.zeros(64), w1=rng.normal(0, 0.2, (64, 64)),
                  b1=np.zeros(64), w2=rng.normal(0, 0.2, (64, 2)), b2=np.array([0.5, 0.0]))
    np.savez(path, **{k: v.astype(np.float32) for k, v in arrays.items()})
    return path


def test_same_seed_same_trial_in_lockstep(tmp_path):
    """Trials through reset with the same seed are identical when the controller reports a fixed
    compute time (a measured one jitters by microseconds, and lockstep charges it)."""
    # one program entry: the scripted controller's program position does not restart per trial
    ctrl = Controller("turning", ("scripted", "--program", "0.7,0.25,100000", "--compute-ms", "13"),
                      "scripted", "racecav.services.sim.scripted")
    with Harness(load_config(), ctrl, "lockstep", "head-to-head", tmp_path / "logs") as h:
        h.set_scenario("head-to-head")
        a, b, c = h.run_trial(0, 11), h.run_trial(1, 11), h.run_trial(2, 12)
    assert a.trajectory == b.trajectory and (a.success, a.progress_m, a.min_gap_m) == (b.success, b.progress_m, b.min_gap_m)
    assert c.trajectory.obstacles != a.trajectory.obstacles  # another seed, another obstacle start
    assert a.compute_ms.median == pytest.approx(13.0)


def test_policy_service_with_other_weights(tmp_path):
    """`--model PATH` evaluates a policy file (weights of the right shape) through the policy service."""
    import hashlib

    model = _random_policy(tmp_path / "rand.npz")
    out = tmp_path / "r.json"
    r = _eval(tmp_path, "--scenario", "head-to-head", "--controller", "drl-default", "--model", str(model),
              "--trials", "1", "--json", str(out))
    assert r.returncode == 0, r.stdout + r.stderr
    res = validate_run(out)
    t = res.trials[0]
    assert res.controller.command == ["racecav", "policy", "--model", str(model.resolve())]
    assert res.controller.weights_sha256 == hashlib.sha256(model.read_bytes()).hexdigest()
    assert t.commands >= t.steps - 1 and t.compute_ms.n == t.commands and 0 < t.compute_ms.median < 50
    assert res.controller_counters["answered"] >= t.steps - 1 and res.controller_counters["malformed"] == 0
    r = _eval(tmp_path, "--scenario", "head-to-head", "--controller", "mpc-apf", "--model", str(model), "--trials", "1")
    assert r.returncode == 2 and "--model applies to the drl-* controllers" in r.stderr
    # a suite runs the same file (--suite once ran the shipped weights whatever --model said)
    from racecav.evaluation import suite as S

    S.generate(S.load_families("open"), tmp_path / "open", n_test=1, n_train=1, seed=1, progress=False)
    out = tmp_path / "suite.json"
    r = _eval(tmp_path, "--suite", str(tmp_path / "open"), "--controller", "drl-default", "--model", str(model),
              "--trials-per-scenario", "1", "--json", str(out))
    assert r.returncode == 0, r.stdout + r.stderr
    assert json.loads(out.read_text())["weights_sha256"] == [hashlib.sha256(model.read_bytes()).hexdigest()]
    r = _eval(tmp_path, "--suite", str(tmp_path / "open"), "--controller", "drl-default", "--model", str(model),
              "--ray")
    assert r.returncode == 2 and "--model runs locally" in r.stderr


@pytest.mark.parametrize("name", ["drl-avoid", "drl-reversed", "drl-default", "drl-racing", "mpc-apf"])
def test_shipped_controllers_run_under_the_harness(tmp_path, name):
    ctrl = CONTROLLERS[name]
    why = missing(ctrl)
    if why:
        pytest.skip(why)
    r = _eval(tmp_path, "--scenario", "head-to-head", "--controller", name, "--trials", "1",
              "--json", str(tmp_path / "r.json"), timeout=180)
    assert r.returncode == 0, r.stdout + r.stderr
    res = validate_run(tmp_path / "r.json")
    t = res.trials[0]
    assert res.complete and res.controller.service == ctrl.service
    assert t.commands >= t.steps - 1 and t.compute_ms.n == t.commands and t.latency_ms.n > 0
    # the same trial seed as everywhere: the obstacle starts where scenario sampling puts it
    assert json.loads((tmp_path / "r.json").read_text())["base_seed"] == 0


def test_eval_realtime_mode(tmp_path):
    r = _eval(tmp_path, "--scenario", "head-to-head", "--controller", "scripted", "--trials", "1", "--mode", "realtime",
              "--json", str(tmp_path / "r.json"))
    assert r.returncode == 0, r.stdout + r.stderr
    res = validate_run(tmp_path / "r.json")
    t = res.trials[0]
    assert res.mode == "realtime" and t.collided and t.wall_s >= 0.8 * t.end_time_s  # ran on the wall clock


def test_table_writes_the_document(tmp_path):
    doc = tmp_path / "results.md"
    suite = tmp_path / "suite"  # one test file per family
    g = subprocess.run(procs.racecav_cmd("suite", "generate", "--n", "7", "--n-train", "1", "--out", str(suite),
                                         "--no-progress"), capture_output=True, text=True, timeout=120)
    assert g.returncode == 0, g.stdout + g.stderr
    # the roads section has its own test (tests/test_roads_table.py): its 290 generated files here
    # would be most of this test's time
    r = _eval(tmp_path, "--table", "--controllers", "scripted", "--trials", "1", "--trials-per-scenario", "1",
              "--sections", "table1,conflict,suite,free", "--suite", str(suite), "--doc", str(doc), timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    text = doc.read_text()
    assert "racecav eval --table --trials 1" in text and "--trials-per-scenario 1" in text and "--suite" in text
    assert "| no evasion (straight 1 m/s, scripted) | **0** [0, 79] | - |" in text  # 0/1 collides, Wilson CI
    for sc in ("right-to-left", "head-to-head", "left-to-right"):
        assert validate_run(tmp_path / "table" / f"scripted-{sc}.json").complete
        assert validate_run(tmp_path / "table" / f"scripted-conflict-{sc}.json").complete
    assert "## Conflict-timed paper scenarios" in text and "## Conflict suite" in text
    assert "| no evasion (straight 1 m/s, scripted) | **0** [0, 79] | **0** [0, 79] | **0** [0, 79] |" in text
    for png in ("results-table1.png", "results-fig4.png", "results-conflict.png", "results-suite.png"):
        assert (tmp_path / "img" / png).stat().st_size > 10_000
    # the free intersections: the open suite's test split (20 files), which a car at 1 m/s fails (too slow)
    assert "## Free intersections" in text
    assert "| no evasion (straight 1 m/s, scripted) | **0** [0, 16] | 0 |" in text, text
    # a controller that cannot run is named, nothing is started
    r = _eval(tmp_path, "--table", "--controllers", "scripted,nonsense", "--trials", "1", "--doc", str(doc))
    assert r.returncode == 2 and "nonsense" in r.stderr


def _tables(text: str) -> list[str]:
    """The document's table rows and section heads: what a store must reproduce (the header line
    holds the date and the wall time, the last section the out-dir)."""
    return [x for x in text.splitlines() if x.startswith(("|", "#"))]


def test_table_store_rewrites_the_document_without_running_a_trial(tmp_path):
    """Every complete cell goes to the committed store beside the document; with --resume a fresh
    out-dir (a fresh clone: no JSONL) gets the same document from it without starting a service,
    and a cell asked with another trial count is run again, not taken from the store."""
    import gzip

    doc = tmp_path / "docs" / "results.md"
    args = ("--table", "--controllers", "full-throttle", "--sections", "table1,free", "--trials-per-scenario", "1",
            "--doc", str(doc))
    r = _eval(tmp_path / "one", *args, "--trials", "2", timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    first = doc.read_text()
    store = tmp_path / "docs" / "results-data"
    assert sorted(p.name for p in store.iterdir()) == ["full-throttle.scenarios.json.gz",
                                                        "full-throttle.suite-open.json.gz"]
    cells = json.loads(gzip.open(store / "full-throttle.scenarios.json.gz").read())
    assert sorted(cells) == ["head-to-head", "left-to-right", "right-to-left"]
    for cell in cells.values():  # compact: outcomes kept, per-step latencies and later trajectories dropped
        run = validate_run(cell)
        assert run.complete and [t.index for t in run.trials] == [0, 1]
        assert run.summary.latency_ms.n > 0 and all(not t.latency_steps_ms for t in run.trials)
        assert run.trials[0].trajectory is not None and run.trials[1].trajectory is None
    assert len(json.loads(gzip.open(store / "full-throttle.suite-open.json.gz").read())) == 20
    doc.unlink()
    r = _eval(tmp_path / "fresh", *args, "--trials", "2", "--resume", timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert _tables(doc.read_text()) == _tables(first)
    assert not list((tmp_path / "fresh").rglob("*.jsonl")) and not (tmp_path / "fresh" / "table" / "logs").exists()
    assert "## Free intersections" in first and "| no evasion (straight, full throttle, scripted) | **100**" in first
    # another trial count is another cell: run, and stored in place of the old one
    r = _eval(tmp_path / "fresh", "--table", "--controllers", "full-throttle", "--sections", "table1",
              "--doc", str(doc), "--trials", "3", "--resume", timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert len(list((tmp_path / "fresh" / "table").glob("*.jsonl"))) == 3
    assert [len(c["trials"]) for c in json.loads(gzip.open(store / "full-throttle.scenarios.json.gz").read()).values()] \
        == [3, 3, 3]
    # --from-store runs nothing: a cell it lacks (here: 4 trials) is an error naming the row
    r = _eval(tmp_path / "none", *args, "--trials", "4", "--from-store", timeout=60)
    assert r.returncode == 2 and "no current cell for 3 of full-throttle's cells" in r.stderr, r.stderr
    assert not (tmp_path / "none" / "table" / "logs").exists()
    # a broken store file is named, nothing is started
    (store / "full-throttle.scenarios.json.gz").write_bytes(b"not gzip")
    r = _eval(tmp_path / "fresh", *args, "--trials", "3", "--resume", timeout=60)
    assert r.returncode == 2 and "full-throttle.scenarios.json.gz" in r.stderr, r.stdout + r.stderr


def test_a_store_sees_the_cells_another_process_wrote(tmp_path):
    """--jobs: the parent read the store before its children wrote their rows; it must see them
    afterwards (else it starts every row's services again to replay the JSONL)."""
    import gzip

    from racecav.evaluation.store import CellStore, stored_key

    repo = Path(__file__).resolve().parents[1]
    cells = json.loads(gzip.open(repo / "docs" / "results-data" / "full-throttle.scenarios.json.gz").read())
    res = validate_run(cells["head-to-head"])
    parent, child = CellStore(tmp_path), CellStore(tmp_path)
    cell = ("full-throttle", "scenarios", "head-to-head")
    assert parent.get(*cell, stored_key(res), res.trials_requested) is None
    child.put(*cell, res)
    got = parent.get(*cell, stored_key(res), res.trials_requested)
    assert got is not None and [(t.seed, t.success) for t in got.trials] == [(t.seed, t.success) for t in res.trials]


def test_code_drift_names_the_trial_code_changed_since_a_cell_was_measured(tmp_path):
    """The store's key has no code digest: the table names the trial-code files changed since the
    commit a reused cell records (a changed table writer is not trial code), and says when git
    cannot tell."""
    from racecav.evaluation.store import code_drift, drift_text

    def git(*a):
        return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *a], cwd=tmp_path,
                              check=True, capture_output=True, text=True).stdout.strip()

    git("init", "-q")
    for f in ("sim/world.py", "evaluation/table.py", "evaluation/trials.py"):
        (tmp_path / f).parent.mkdir(exist_ok=True)
        (tmp_path / f).write_text("x = 1\n")
    git("add", "-A")
    git("commit", "-qm", "measured here")
    rev = git("rev-parse", "--short=12", "HEAD")
    assert code_drift([rev, rev + "-dirty"], tmp_path) == {rev: [], rev + "-dirty": []}
    (tmp_path / "evaluation" / "table.py").write_text("x = 2\n")  # writes the document only
    assert code_drift([rev], tmp_path) == {rev: []}
    (tmp_path / "sim" / "world.py").write_text("x = 2\n")
    (tmp_path / "evaluation" / "trials.py").write_text("x = 2\n")
    drift = code_drift([rev, "unknown"], tmp_path)
    assert drift == {rev: ["evaluation/trials.py", "sim/world.py"], "unknown": None}
    text = drift_text({rev: 3, "unknown": 1}, drift)
    assert f"since {rev}: evaluation/trials.py, sim/world.py" in text and "git cannot compare unknown" in text
    assert "has not changed" in drift_text({rev: 3}, {rev: []}) and drift_text({}, {}) == ""


@pytest.mark.timeout(1200)  # a fresh clone first generates the suites' evaluation splits (conflicts, open, roads)
def test_committed_results_are_what_the_committed_store_writes(tmp_path):
    """docs/results.md is what its own command (from its header) writes from the committed cells
    (docs/results-data) alone: every number of its tables comes from a stored cell measured with the
    shipped weights and scenario files, none is typed by hand or left over from an older run."""
    import re

    repo = Path(__file__).resolve().parents[1]
    committed = (repo / "docs" / "results.md").read_text()
    cmd = re.search(r"Written by `racecav eval (--table[^`]*)`", committed).group(1).split()
    doc = tmp_path / "results.md"
    r = _eval(tmp_path / "out", *cmd, "--from-store", "--store", str(repo / "docs" / "results-data"),
              "--doc", str(doc), timeout=1150)
    assert r.returncode == 0, r.stdout + r.stderr
    assert _tables(doc.read_text()) == _tables(committed)
    assert not list((tmp_path / "out").rglob("*.jsonl"))


def test_safety_both_needs_the_table(tmp_path):
    """--safety both is a table option (its cells run in test_table_jobs_split_...)."""
    r = _eval(tmp_path, "--scenario", "head-to-head", "--controller", "scripted", "--safety", "both")
    assert r.returncode == 2 and "--table" in r.stderr


def test_table_jobs_split_the_controllers_over_processes(tmp_path):
    """--jobs 2: two child tables (one controller row each) fill the cells, then the document is
    written from them; a cell equals the one a single process computes (lockstep: same seeds,
    same outcomes; the measured compute time it charges moves the car by micrometres)."""
    doc = tmp_path / "results.md"
    r = _eval(tmp_path / "two", "--table", "--controllers", "scripted,full-throttle", "--sections", "table1",
              "--trials", "2", "--jobs", "2", "--doc", str(doc), timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "job 0: scripted" in r.stdout and "job 1: full-throttle" in r.stdout
    for k in (0, 1):
        assert (tmp_path / "two" / "table" / "logs" / f"job-{k}.log").is_file()
    text = doc.read_text()
    assert "| no evasion (straight 1 m/s, scripted) |" in text and "| no evasion (straight, full throttle" in text
    r = _eval(tmp_path / "one", "--table", "--controllers", "full-throttle", "--sections", "table1", "--trials", "2",
              "--doc", str(tmp_path / "one.md"), timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    for sc in ("right-to-left", "head-to-head", "left-to-right"):
        two, one = (validate_run(tmp_path / d / "table" / f"full-throttle-{sc}.json") for d in ("two", "one"))
        assert two.complete and [(t.seed, t.success, t.steps) for t in two.trials] == \
            [(t.seed, t.success, t.steps) for t in one.trials]
        assert np.allclose([t.progress_m for t in two.trials], [t.progress_m for t in one.trials], atol=1e-3)
    # resumed with the supervisor rows added: only the rows with trials left get a process
    r = _eval(tmp_path / "two", "--table", "--controllers", "scripted,full-throttle", "--sections", "table1",
              "--trials", "2", "--jobs", "2", "--safety", "both", "--resume", "--doc", str(doc), timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "job 0: scripted+safety, 6 trials" in r.stdout and "job 1: full-throttle+safety, 6 trials" in r.stdout
    assert "job 2:" not in r.stdout, r.stdout
    text = doc.read_text()
    assert "--safety both" in text and "## Emergency-brake supervisor on/off" in text  # from both rows of each
    for sc in ("right-to-left", "head-to-head", "left-to-right"):  # every cell without and with the supervisor
        off = json.loads((tmp_path / "two" / "table" / f"scripted-{sc}.json").read_text())
        on = json.loads((tmp_path / "two" / "table" / f"scripted-{sc}-safety.json").read_text())
        assert off["controller"]["name"] == "scripted" and on["controller"]["name"] == "scripted+safety"
    row = next(line for line in text.splitlines() if line.startswith("| no evasion") and "->" in line)
    assert row.count("->") == 3 * 2  # success and collisions, off -> on, per scenario
    r = _eval(tmp_path, "--table", "--controllers", "scripted", "--jobs", "0", "--doc", str(doc))
    assert r.returncode == 2 and "--jobs" in r.stderr


def test_demo_runs_the_shipped_avoid_policy(tmp_path):
    if missing(CONTROLLERS["drl-avoid"]):
        r = subprocess.run(procs.racecav_cmd("demo", "--out-dir", str(tmp_path)), capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 1 and "avoid.npz" in r.stderr and "Nothing was started" in r.stderr
        return
    r = subprocess.run(procs.racecav_cmd("demo", "--trials", "1", "--out-dir", str(tmp_path)), capture_output=True,
                       text=True, timeout=180)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "trial 0 (seed 0)" in r.stdout and "scan->command latency median" in r.stdout
    assert (tmp_path / "head-to-head-drl-avoid.png").exists()
