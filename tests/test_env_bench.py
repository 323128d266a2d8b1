"""`racecav bench env` runs end to end (tiny durations; no timing is asserted: benchmarks, not
tests, check performance)."""

import json
import subprocess
import sys


def test_bench_env_runs_and_reports(tmp_path):
    out = tmp_path / "env.json"
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "bench", "env", "--seconds", "0.6",
                        "--bullet-seconds", "1.0", "--n-envs", "8", "--no-doc", "--json", str(out)],
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-2000:]
    data = json.loads(out.read_text())
    for key in ("fast_1proc_all_lidar", "fast_2proc_all_lidar_total", "fast_vecenv_training_config",
                "bullet_all_lidar", "bullet_agent_lidar"):
        assert data[key]["wall"]["median"] > 0 and data[key]["cpu"]["median"] > 0, key
    assert len(data["fast_2proc_per_process_median"]) == 2
    assert data["ratio_fast_1proc_vs_bullet_all_lidar"] > 1.0
    assert "Ratio fast" in r.stdout
