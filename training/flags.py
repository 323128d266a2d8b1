"""The settings of ``racecav train racing|overtake|dagger`` that are flags: fields of TrainConfig
and EnvConfig (common/config.py), whose docstrings and defaults are the flags' help
(training/train.py) and docs/training.md's flag table (training/report.py); and the run's
TrainConfig they make."""

from __future__ import annotations

TRAIN_FLAGS = ("seed", "n_steps", "batch_size", "n_epochs", "gamma", "learning_rate", "gae_lambda",
               "clip_range", "ent_coef", "vf_coef", "max_grad_norm", "normalize", "checkpoint_every",
               "init_from", "init_std", "sde_sample_freq", "hidden")
"""TrainConfig fields that are flags of ``racecav train racing|overtake|dagger`` (--name-with-dashes)."""
DAGGER_FLAGS = ("expert", "mirror_families", "expert_share", "grad_steps", "dataset_max", "bc_balance",
                "map_resample_every")
"""TrainConfig fields that are flags of ``racecav train dagger``."""
ENV_FLAGS = {"heading": "--heading", "n_envs": "--n-envs", "n_obstacles": "--n-obstacles", "driver": "--driver",
             "time_limit_s": "--time-limit", "world": "--world", "scenarios": "--scenarios",
             "scenario_share": "--scenario-share", "obs_stack": "--obs-stack", "obs_stride": "--obs-stride",
             "flow_reward": "--flow-reward", "progress_reward": "--progress-reward", "brake_below": "--brake-below",
             "curriculum": "--curriculum", "curriculum_boost": "--curriculum-boost", "lidar": "--lidar",
             "scenario_maps": "--scenario-maps"}
"""EnvConfig fields that are flags (field -> flag)."""


def config_from_args(args, env_base=None):
    """The run's TrainConfig: defaults, the preset, the stage's env defaults, explicit flags.

    :param env_base: the EnvConfig of the configuration file (``--config``) to start from.
    :raises ValueError: naming the invalid setting.
    """
    from pydantic import ValidationError

    from racecav.common.config import TRAIN_PRESETS, TrainConfig
    from racecav.common.vehicle import format_errors

    overtake = args.stage != "racing"  # overtake, dagger: the overtaking env
    preset = TRAIN_PRESETS[args.preset]
    env = {**(env_base.model_dump() if env_base is not None else {}), **preset.get("env", {}),
           "heading": "default", "n_obstacles": 15 if overtake else 0,
           "driver": "policy:racing" if overtake else "centerline"}
    flags = {k: getattr(args, f"env_{k}", None) for k in ENV_FLAGS}
    env.update({k: v for k, v in flags.items() if v is not None})
    if not overtake and flags.get("heading") not in (None, "default"):
        raise ValueError("heading: the racing stage drives with no traffic (default heading only)")
    if env.get("scenarios") and flags.get("scenario_share") is None:
        env["scenario_share"] = 0.5
    data = {**{k: v for k, v in preset.items() if k != "env"}, "stage": args.stage, "preset": args.preset,
            **{k: getattr(args, k) for k in TRAIN_FLAGS + DAGGER_FLAGS if getattr(args, k, None) is not None}, "env": env}
    if data.get("init_from") is not None:
        data["init_from"] = str(data["init_from"])
    try:
        return TrainConfig.model_validate(data)
    except ValidationError as e:
        raise ValueError(format_errors(e)) from None


def stage_defaults(stage: str, preset: str) -> dict:
    """The settings a run of ``stage`` gets without flags under ``preset``: TrainConfig's fields
    and ``env.``-prefixed EnvConfig fields (config_from_args' order: defaults, preset, stage)."""
    from argparse import Namespace

    tc = config_from_args(Namespace(stage=stage, preset=preset))
    return {**tc.model_dump(exclude={"env"}), **{f"env.{k}": v for k, v in tc.env.model_dump().items()}}
