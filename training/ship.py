"""``racecav train ship --run-dir DIR --checkpoint best|latest|STEP --name NAME [--recipe R]``:
writes common/data/policies/NAME.{npz,json,zip,vecnorm.pkl} (with ``--recipe``, the metadata
names the recipe, its digest and the stage the run is) and copies the run's learning curve,
settings and evaluation to training/checkpoints/RUN/ (committed: the report and ``--resume``
across sessions need them)."""

from __future__ import annotations

import csv
import json
import logging
import shutil

from racecav.common.lidar import VIEWS
from racecav.training.runs import checkpoints, load_run_config, save_run_record, step_of

log = logging.getLogger("racecav.train")


def ship(args, cfg) -> int:
    from stable_baselines3 import PPO

    from racecav.common.policy import MODELS_DIR, export_policy
    from racecav.common.bench import git_commit

    run_dir = args.run_dir
    tc, record = load_run_config(run_dir)
    evals = {}
    if (run_dir / "eval.csv").is_file():
        with (run_dir / "eval.csv").open() as f:
            evals = {int(r["timesteps"]): r for r in csv.DictReader(f)}
    if args.checkpoint == "best":
        best = json.loads((run_dir / "best.json").read_text())
        ck = run_dir / "checkpoints" / best["checkpoint"]
    elif args.checkpoint == "latest":
        ck = checkpoints(run_dir)[-1]
    else:
        ck = run_dir / "checkpoints" / f"step_{int(float(args.checkpoint)):09d}.zip"
    if not ck.is_file():
        log.error("ship: no checkpoint %s", ck)
        return 2
    recipe = None
    if getattr(args, "recipe", None):
        from racecav.training.recipe import RecipeError, recipe_record

        try:
            recipe = recipe_record(args.recipe, run_dir)
        except RecipeError as e:
            print(f"racecav train ship: {e}")
            return 2
    model = PPO.load(ck, device="cpu")
    norm = None
    vn = ck.with_suffix(".vecnorm.pkl")
    if vn.is_file():
        import pickle

        with vn.open("rb") as f:
            norm = pickle.load(f)
    n = step_of(ck)
    latest = json.loads((run_dir / "latest.json").read_text()) if (run_dir / "latest.json").is_file() else {}
    meta = {"name": args.name, "training_steps": n, "run": run_dir.name, "checkpoint": ck.name,
            "seed": tc.seed, "settings": tc.model_dump(mode="json"), "git_commit_training": record.get("git_commit"),
            "git_commit_export": git_commit(),
            "run_total_steps": latest.get("timesteps"), "run_wall_s": latest.get("wall_s"),
            "selection": evals.get(n), "obs_stack": tc.env.obs_stack, "obs_stride": tc.env.obs_stride,
            "lidar": tc.env.lidar,
            "observation": (f"sanitised lidar ranges (common/lidar.sanitize), the {tc.env.lidar!r} view "
                            f"(common/lidar.VIEWS, {VIEWS[tc.env.lidar].n_rays} rays), m"
                            + (f"; {tc.env.obs_stack} scans {tc.env.obs_stride} scan period(s) apart, newest first"
                               if tc.env.obs_stack > 1 else "")),
            "action": "[a_T, a_delta] in [-1, 1]: Gaussian mean (deterministic)"
                      + (f"; a_T < {tc.env.brake_below} brakes" if tc.env.brake_below is not None else ""),
            "brake_below": tc.env.brake_below}
    if recipe is not None:
        meta["recipe"] = recipe
    dst = MODELS_DIR / f"{args.name}.npz"
    export_policy(model, dst, meta, obs_rms=norm.obs_rms if norm else None,
                  clip_obs=norm.clip_obs if norm else 10.0, epsilon=norm.epsilon if norm else 1e-8)
    shutil.copyfile(ck, dst.with_suffix(".zip"))
    if vn.is_file():
        shutil.copyfile(vn, MODELS_DIR / f"{args.name}.vecnorm.pkl")
    save_run_record(run_dir)
    print(f"shipped {ck} as {dst} (+ .json, .zip)")
    return 0
