"""The settings of ``racecav train racing|overtake|dagger`` that are flags: fields of TrainConfig
and EnvConfig (common/config.py), whose docstrings and defaults are the flags' help
(training/train.py) and docs/training.md's flag table (training/report.py)."""

TRAIN_FLAGS = ("seed", "n_steps", "batch_size", "n_epochs", "gamma", "learning_rate", "gae_lambda",
               "clip_range", "ent_coef", "vf_coef", "max_grad_norm", "normalize", "checkpoint_every",
               "init_from", "init_std", "sde_sample_freq", "hidden")
"""TrainConfig fields that are flags of ``racecav train racing|overtake|dagger`` (--name-with-dashes)."""
DAGGER_FLAGS = ("expert", "mirror_families", "expert_share", "grad_steps", "dataset_max", "bc_balance")
"""TrainConfig fields that are flags of ``racecav train dagger``."""
ENV_FLAGS = {"heading": "--heading", "n_envs": "--n-envs", "n_obstacles": "--n-obstacles", "driver": "--driver",
             "time_limit_s": "--time-limit", "world": "--world", "scenarios": "--scenarios",
             "scenario_share": "--scenario-share", "obs_stack": "--obs-stack", "obs_stride": "--obs-stride",
             "flow_reward": "--flow-reward", "progress_reward": "--progress-reward", "brake_below": "--brake-below",
             "curriculum": "--curriculum", "curriculum_boost": "--curriculum-boost", "lidar": "--lidar"}
"""EnvConfig fields that are flags (field -> flag)."""
