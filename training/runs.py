"""A training run's record: its settings (config.json: a TrainConfig plus who and when)."""

from __future__ import annotations

import csv
import json
import logging
import os
import time
from pathlib import Path

log = logging.getLogger("racecav.train")

RECORD_KEYS = ("git_commit", "started", "total_steps")
"""Keys of a run's config.json that describe the run, not its settings."""


def run_dir_of(zip_path: Path) -> Path:
    """The run folder of a checkpoint (``<run>/checkpoints/step_N.zip``) or of ``<run>/latest.zip``."""
    zip_path = Path(zip_path)
    return zip_path.parent.parent if zip_path.parent.name == "checkpoints" else zip_path.parent


def source_env(path: Path, key: str, default):
    """An env setting a policy zip was trained with: its metadata (a shipped policy's .json),
    else its run's config.json (a checkpoint), else ``default``."""
    meta = Path(path).with_suffix(".json")
    if meta.is_file() and key in (m := json.loads(meta.read_text())):
        return m[key]
    run_dir = run_dir_of(path)
    if (run_dir / "config.json").is_file():
        return getattr(load_run_config(run_dir)[0].env, key)
    return default


def load_run_config(run_dir: Path):
    """(TrainConfig, record) of a run folder's config.json; reads the flat format of runs made
    before TrainConfig existed (training/checkpoints/*/config.json)."""
    from racecav.common.config import TrainConfig

    data = json.loads((Path(run_dir) / "config.json").read_text())
    record = {k: data.pop(k) for k in RECORD_KEYS if k in data}
    if "env" not in data:  # flat: PPO settings and env settings side by side
        env = {"n_envs": data.pop("n_envs", 1), "heading": data.pop("heading", "default"),
               "n_obstacles": data.pop("n_obstacles", 15), "driver": data.pop("driver", "centerline"),
               "world": data.pop("world", "racetrack")}
        tl = data.pop("time_limit", None)
        if tl is not None:
            env["time_limit_s"] = tl
        for k in ("scenarios", "scenario_share", "contact_penalty", "obs_stack"):
            if k in data:
                env[k] = data.pop(k)
        data["env"] = env
    return TrainConfig.model_validate(data), record


def save_checkpoint(run_dir: Path, model, vec_normalize, wall_s: float, final: bool = False) -> Path:
    """Write ``checkpoints/step_<N>.zip`` (+ ``.vecnorm.pkl``) of an SB3 model at its
    num_timesteps, then ``latest.*`` as copies, each renamed into place (an interruption never
    leaves half a file), and ``latest.json`` (what ``--resume`` reads)."""
    n = model.num_timesteps
    ck = Path(run_dir) / "checkpoints" / f"step_{n:09d}"
    # written under another name, then renamed into place: a run killed while saving leaves no
    # truncated step_*.zip for select or --resume to trip over; the normalisation first, so that a
    # step_*.zip never stands without its own
    partial = ck.parent / "partial"
    # a run resumed from its committed record (latest.* only) has no checkpoints/ folder yet
    ck.parent.mkdir(parents=True, exist_ok=True)
    if vec_normalize is not None:
        vec_normalize.save(str(partial.with_suffix(".vecnorm.pkl")))
        os.replace(partial.with_suffix(".vecnorm.pkl"), ck.with_suffix(".vecnorm.pkl"))
    model.save(partial.with_suffix(".zip"))
    os.replace(partial.with_suffix(".zip"), ck.with_suffix(".zip"))
    for suffix in (".vecnorm.pkl", ".zip"):  # the normalisation first, as above
        src = ck.with_suffix(suffix)
        if src.is_file():
            tmp = Path(run_dir) / f"latest.tmp{suffix}"
            tmp.write_bytes(src.read_bytes())
            os.replace(tmp, Path(run_dir) / f"latest{suffix}")
    state = {"timesteps": n, "wall_s": round(wall_s, 2), "checkpoint": ck.name, "final": final,
             "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    (Path(run_dir) / "latest.tmp.json").write_text(json.dumps(state) + "\n")
    os.replace(Path(run_dir) / "latest.tmp.json", Path(run_dir) / "latest.json")
    log.info("checkpoint %s (%.0f s wall)", ck.name, wall_s)
    return ck


def truncate_csv(path: Path, timesteps: int, fields: list[str]) -> None:
    """Drop the rows of a run's CSV written after the checkpoint being resumed."""
    if not path.is_file():
        return
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if int(float(r["timesteps"])) <= timesteps]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def append_csv(path: Path, fields: list[str], row: dict) -> None:
    """Append one row to a run's CSV, with the header if the file is new or empty."""
    new = not path.is_file() or path.stat().st_size == 0
    with path.open("a", newline="") as f:
        w = csv.DictWriter(f, fields)
        if new:
            w.writeheader()
        w.writerow(row)
