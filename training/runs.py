"""A training run's record: its settings (config.json: a TrainConfig plus who and when)."""

from __future__ import annotations

import csv
import json
import logging
import os
import time
from pathlib import Path

log = logging.getLogger("racecav.train")

REPO = Path(__file__).resolve().parent.parent
COMMITTED = REPO / "training" / "checkpoints"
"""The committed run records (training/checkpoints/<run>/): what the report and a resume need."""
REFERENCES_CSV = COMMITTED / "references.csv"
"""The non-evading references on the selection split (``racecav train references``), beside the ablation."""
IMAGES = REPO / "docs" / "img"
"""Where a run's checkpoint plot goes (training_eval_<run>.png), beside the page that shows it."""
RECORD_KEYS = ("git_commit", "started", "total_steps")
"""Keys of a run's config.json that describe the run, not its settings."""


def checkpoints(run_dir: Path) -> list[Path]:
    """A run's checkpoints, oldest first."""
    return sorted((Path(run_dir) / "checkpoints").glob("step_*.zip"))


def step_of(path: Path) -> int:
    """The sample count of a checkpoint ``step_<N>.zip``."""
    return int(Path(path).stem.split("_")[1])


def save_run_record(run_dir: Path) -> Path:
    """Copy what the report and a resume need into training/checkpoints/<run>/ (committed); the
    checkpoint plot goes to docs/img/training_eval_<run>.png (the page shows it; one copy)."""
    import shutil

    dst = COMMITTED / Path(run_dir).name
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("config.json", "progress.csv", "eval.csv", "best.json", "curriculum.csv",
                 "latest.json", "latest.zip", "latest.vecnorm.pkl"):
        if (Path(run_dir) / name).is_file():
            shutil.copyfile(Path(run_dir) / name, dst / name)
    if (Path(run_dir) / "eval.png").is_file():
        IMAGES.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(Path(run_dir) / "eval.png", IMAGES / f"training_eval_{Path(run_dir).name}.png")
    return dst


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
        for k in ("scenarios", "scenario_share", "contact_penalty", "obs_stack"):  # (contact_penalty: removed below)
            if k in data:
                env[k] = data.pop(k)
        data["env"] = env
    drop_removed(data, run_dir)
    return TrainConfig.model_validate(data), record


EXPERIMENTS_COMMIT = "3a95a65"
"""The commit whose training/ still holds the ablation's rejected experiments (docs/training.md)."""
_ANY = object()
REMOVED_SETTINGS = {
    "mirror_symmetric": False, "mirror_augment": False, "steer_bound_coef": 0.0, "privileged_critic": False,
    "hold_until_seen": False, "hold_families": _ANY, "hold_through": _ANY, "expert_horizon_s": _ANY,
    "expert_seen": False, "expert_commit_s": None, "mirror_seen": False, "anchor_families": "",
    "anchor_from": None, "anchor_seen": False, "aux_seen": 0.0, "bc_coef": 0.0, "bc_label_steps": _ANY,
    "bc_grad_steps": _ANY, "bc_learning_rate": _ANY, "balance_standing": False,
}
"""TrainConfig settings of rejected ablation rows, now gone, with the value that turned each off
(_ANY: it acted only together with another one here)."""
REMOVED_ENV_SETTINGS = {"contact_penalty": 0.0, "lane_keeping": 0.0, "lane_keeping_horizon_s": _ANY,
                        "hold_heading": 0.0, "hold_track": 0.0, "proximity_penalty": 0.0, "perturb": None,
                        "map_curriculum": False, "stand_input": 0.0}
"""The same for EnvConfig."""
REMOVED_AT = {"env.perturb": "dc49441", "env.map_curriculum": "814eb57", "env.stand_input": "814eb57",
              "balance_standing": "079c3b6"}
"""Settings removed after EXPERIMENTS_COMMIT, with the commit that still has their code (training
under randomised perturbations: ablation rows 97-98, docs/robustness.md; the recipe's tried
stages focus, stand and standing: docs/training_notes.md)."""


def drop_removed(data: dict, run_dir) -> None:
    """Take the settings of removed experiments out of a run's config.json data, in place: turned
    off they changed nothing; turned on, the run cannot be reproduced by this code.

    :raises ValueError: naming the setting and the commit that still has its code.
    """
    def check(d: dict, removed: dict, prefix: str) -> None:
        for k, off in removed.items():
            if k in d:
                v = d.pop(k)
                if off is not _ANY and v != off:
                    raise ValueError(f"{run_dir}/config.json: {prefix}{k} = {v!r} is an experiment removed from "
                                     f"training/ (docs/training.md); its code is at commit "
                                     f"{REMOVED_AT.get(prefix + k, EXPERIMENTS_COMMIT)}")

    check(data, REMOVED_SETTINGS, "")
    check(data.get("env", {}), REMOVED_ENV_SETTINGS, "env.")
    # the teacher of a PPO run was never used (only dagger runs imitate); dagger's other teachers are
    # gone: the ones TrainConfig.expert does not name
    from typing import get_args

    from racecav.common.config import TrainConfig

    if data.get("expert") not in (None, *get_args(TrainConfig.model_fields["expert"].annotation)):
        if data.get("stage") == "dagger":
            raise ValueError(f"{run_dir}/config.json: expert = {data['expert']!r} is a teacher removed from "
                             f"training/ (docs/training.md); its code is at commit {EXPERIMENTS_COMMIT}")
        data.pop("expert")


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
