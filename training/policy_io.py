"""A run's checkpoint as a driver: the NumpyPolicy of an SB3 zip with its run's view settings."""

from __future__ import annotations

from pathlib import Path

from racecav.training.runs import load_run_config, run_dir_of


def policy_from_checkpoint(zip_path: Path, obs_stack: int = 1, brake_below: float | None = None,
                           lidar: str = "paper", obs_stride: int = 1):
    """NumpyPolicy of an SB3 checkpoint (+ its ``.vecnorm.pkl`` normalisation if present); the
    arguments are the run's env settings its metadata records (EnvConfig)."""
    import pickle

    from stable_baselines3 import PPO

    from racecav.common.policy import NumpyPolicy, policy_arrays_from_sb3

    model = PPO.load(zip_path, device="cpu")
    arrays = policy_arrays_from_sb3(model)
    vn = zip_path.with_suffix(".vecnorm.pkl")
    if vn.is_file():
        with vn.open("rb") as f:
            norm = pickle.load(f)
        n_in = arrays["w0"].shape[0]  # the actor's inputs (a privileged critic reads more)
        arrays.update(obs_mean=norm.obs_rms.mean[:n_in], obs_var=norm.obs_rms.var[:n_in],
                      obs_clip=norm.clip_obs, obs_eps=norm.epsilon)
    return NumpyPolicy(arrays, {"obs_stack": obs_stack, "obs_stride": obs_stride, "brake_below": brake_below,
                                "lidar": lidar})


def checkpoint_policy(zip_path: Path):
    """NumpyPolicy of a run's checkpoint (``<run>/checkpoints/step_N.zip`` or ``<run>/latest.zip``)
    with the env settings of the run's config.json (its view, stack, stride and brake)."""
    zip_path = Path(zip_path)
    if not zip_path.is_file():
        raise FileNotFoundError(f"checkpoint {zip_path}: no such file")
    run_dir = run_dir_of(zip_path)
    if not (run_dir / "config.json").is_file():
        raise FileNotFoundError(f"checkpoint {zip_path}: no run record {run_dir / 'config.json'} (its env settings)")
    env = load_run_config(run_dir)[0].env
    return policy_from_checkpoint(zip_path, env.obs_stack, env.brake_below, env.lidar, env.obs_stride)


def named_policy(spec: str):
    """A shipped policy's name or an .npz (common/policy.load_policy), or a run's checkpoint .zip
    with its run's settings (checkpoint_policy): the ``--policy`` of ``racecav train paths``."""
    from racecav.common.policy import load_policy

    return checkpoint_policy(Path(spec)) if spec.endswith(".zip") else load_policy(spec)
