"""A training run's record: its settings (config.json: a TrainConfig plus who and when)."""

from __future__ import annotations

import json
from pathlib import Path

RECORD_KEYS = ("git_commit", "started", "total_steps")
"""Keys of a run's config.json that describe the run, not its settings."""


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
