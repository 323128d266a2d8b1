"""Lockstep cells repeat bit for bit whatever the machine's load: the sim charges every command
the controller's benchmarked compute time (registry charge_ms), not the one it measured. (With
``--compute-charge measured`` the same two runs differ: progress 10.506317 vs 10.506320 m on
conflict-right-to-left, checked when this test was written.)"""

import subprocess
import sys

from racecav.common import procs, registry
from racecav.evaluation.results import validate_run


def _run(tmp_path, name: str, *extra) -> object:
    out = tmp_path / f"{name}.json"
    r = subprocess.run(procs.racecav_cmd("eval", "--scenario", "right-to-left", "--controller", "drl-avoid",
                                         "--trials", "1", "--json", str(out), "--out-dir", str(tmp_path),
                                         "--no-progress", *extra), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    return validate_run(out)


def test_one_cell_twice_the_second_beside_busy_processes(tmp_path):
    quiet = _run(tmp_path, "quiet")
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        loaded = _run(tmp_path, "loaded")
    finally:
        for p in busy:
            p.kill()
            p.wait()
    charge = registry.CONTROLLERS["drl-avoid"].charge_ms
    for res in (quiet, loaded):
        assert res.controller.compute_charge_ms == charge and res.sim_counters["lockstep_compute_ms"] == charge
    outcome = lambda t: (t.seed, t.success, t.contact_with, t.steps, t.end_time_s, t.progress_m, t.min_gap_m,  # noqa: E731
                         t.trajectory, t.measures)
    assert [outcome(t) for t in quiet.trials] == [outcome(t) for t in loaded.trials]
    # the load was real: the controller measured other compute times (which are no longer charged)
    assert [t.compute_steps_ms for t in quiet.trials] != [t.compute_steps_ms for t in loaded.trials]
