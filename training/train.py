"""The training runs behind ``racecav train`` (its command line: training/cli.py): PPO and DAgger
on a run folder, resumable.

Stable-baselines3 PPO, MlpPolicy net_arch [64, 64] tanh. ``--preset paper`` (the default) is the
paper's setting: one env, n_steps 2048, batch 64, 10 epochs, gamma 0.99, lr 3e-4, no
normalisation. ``--preset fast`` is what the shipped policies were trained with on 2 CPU cores
(docs/training.md): 64 batched envs, larger minibatches, observation normalisation. Every
setting is also a flag that overrides the preset.

A run lives in ``--run-dir``: ``config.json`` (all settings, fixed at the first start),
``progress.csv`` (one row per PPO iteration: the learning curve), ``checkpoints/step_<N>.zip``
(+ ``step_<N>.vecnorm.pkl`` with the normalisation statistics), ``latest.zip``/``latest.vecnorm.pkl``.
Checkpoints are written every ``--checkpoint-every`` samples, after a PPO update (so the saved
optimizer state and step count belong together), and on SIGTERM/SIGINT. ``--resume`` reloads
``latest`` (weights, Adam state, num_timesteps, normalisation statistics), cuts the CSV back to
that step and continues to ``--steps`` (the total). Samples of a rollout interrupted by a signal
are discarded (the step count is restored to the last update).
"""

from __future__ import annotations

import csv
import json
import logging
import pickle
import signal
import time
from pathlib import Path

from racecav.common.bench import git_commit
from racecav.common.lidar import VIEWS
from racecav.training.runs import load_run_config, save_checkpoint, source_env, truncate_csv

log = logging.getLogger("racecav.train")

CSV_FIELDS = ["timesteps", "wall_s", "samples_per_s", "ep_rew_mean", "ep_len_mean", "ep_count",
              "approx_kl", "clip_fraction", "entropy_loss", "value_loss", "policy_gradient_loss",
              "explained_variance", "std", "learning_rate"]


# ----------------------------------------------------------------------------------- settings
def make_venv(tc, seed: int):
    """The (VecMonitor-wrapped) FastVecEnv of a run's TrainConfig."""
    from stable_baselines3.common.vec_env import VecMonitor

    from racecav.training.vec_env import FastVecEnv

    return VecMonitor(FastVecEnv(config=tc.env, seed=seed))


def _ppo_kwargs(tc) -> dict:
    import torch

    policy_kwargs = dict(net_arch=[tc.hidden, tc.hidden], activation_fn=torch.nn.Tanh)
    sde = {} if tc.sde_sample_freq is None else dict(use_sde=True, sde_sample_freq=tc.sde_sample_freq)
    return dict(**sde, n_steps=tc.n_steps, batch_size=tc.batch_size, n_epochs=tc.n_epochs, gamma=tc.gamma,
                learning_rate=tc.learning_rate, gae_lambda=tc.gae_lambda, clip_range=tc.clip_range,
                ent_coef=tc.ent_coef, vf_coef=tc.vf_coef, max_grad_norm=tc.max_grad_norm,
                policy_kwargs=policy_kwargs)


# ----------------------------------------------------------------------------------- training
def train_ppo(run_dir: Path, tc, state: dict, total: int, resume: bool, progress: bool = True) -> int:
    """PPO on the run in ``run_dir`` (opened by training/cli.py, or by the recipe runner) until ``total``
    samples or a signal; ``resume``: load ``latest`` instead of starting new weights."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    torch.set_num_threads(1)
    limit_blas_threads(1)
    # Env seed: the run's seed, shifted on resume so a resumed run does not replay its episodes.
    venv = make_venv(tc, seed=tc.seed + state["timesteps"])
    if tc.normalize:
        if resume:
            venv = VecNormalize.load(str(run_dir / "latest.vecnorm.pkl"), venv)
            venv.training = True
        else:
            venv = init_normalization(VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=tc.gamma), tc)
    if resume:
        model = PPO.load(run_dir / "latest.zip", env=venv, device="cpu")
        truncate_csv(run_dir / "progress.csv", model.num_timesteps, CSV_FIELDS)
        log.info("resumed %s at %d samples", run_dir, model.num_timesteps)
    else:
        model = PPO("MlpPolicy", venv, seed=tc.seed, device="cpu", verbose=0, **_ppo_kwargs(tc))
        if tc.init_from:
            try:
                init_weights(model, Path(tc.init_from), tc.init_std, VIEWS[tc.env.lidar], tc.env.obs_stride)
                if tc.sde_sample_freq is not None:  # the asked noise, else the source's (a gSDE one is loaded)
                    std = tc.init_std or source_std(Path(tc.init_from))
                    if std is not None:
                        calibrate_sde(model, venv.reset(), std)
            except ValueError as e:  # a policy these settings cannot start from
                print(f"racecav train: {e}")
                return 2
    _configure_logger(model, run_dir)
    cb = _make_callback_class()(run_dir, total, tc.checkpoint_every, state["wall_s"], progress=progress)
    callbacks = [cb]
    remaining = total - model.num_timesteps
    if remaining <= 0:
        log.info("run already at %d >= %d samples", model.num_timesteps, total)
        return 0
    old = {sig: signal.signal(sig, cb.request_stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        model.learn(remaining, callback=callbacks, reset_num_timesteps=False, progress_bar=False)
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        cb.close()
    if cb.stop_requested:
        model.num_timesteps = cb.rollout_start_steps  # drop the unfinished rollout
    cb.save(model, final=not cb.stop_requested)
    log.info("%s at %d samples (%s)", run_dir, model.num_timesteps,
             "stopped by signal" if cb.stop_requested else "done")
    return 0


def resume_run(run_dir: Path):
    """(TrainConfig, latest state) of the run in ``run_dir``; None (after saying why) if none."""
    if not (run_dir / "latest.zip").is_file():
        log.error("--resume: no %s", run_dir / "latest.zip")
        return None
    return load_run_config(run_dir)[0], json.loads((run_dir / "latest.json").read_text())


def config_problem(tc) -> str | None:
    """Why a run of ``tc`` cannot start (one line), or None."""
    if tc.sde_sample_freq is not None and tc.stage == "dagger":
        return "racecav train: --sde-sample-freq (gSDE) explores in PPO's rollouts (use it with racecav train overtake)"
    if tc.stage == "dagger" and (not tc.init_from or not tc.normalize):
        return ("racecav train dagger: needs --init-from a policy and normalisation (--preset fast): "
                "the imitation keeps that policy's input statistics")
    return None


def new_run(tc, run_dir: Path) -> dict | None:
    """Record a new run of the TrainConfig ``tc`` in ``run_dir`` (config.json: the settings, the
    commit, the time) and return its start state; None (after saying why) if it cannot start."""
    if (run_dir / "latest.zip").exists():
        log.error("%s already holds a run: use --resume or another --run-dir", run_dir)
        return None
    problem = config_problem(tc)
    if problem:
        print(problem)
        return None
    record = {"git_commit": git_commit(), "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps({**tc.model_dump(mode="json"), **record}, indent=2) + "\n")
    return {"timesteps": 0, "wall_s": 0.0}


def run_dagger(run_dir: Path, tc, state: dict, total: int, resume: bool, progress: bool = True) -> int:
    """DAgger (training/dagger.py) on the run in ``run_dir`` until ``total`` samples or a signal."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from racecav.training.dagger import imitate
    from racecav.training.vec_env import FastVecEnv

    torch.set_num_threads(1)
    limit_blas_threads(1)
    fast = FastVecEnv(config=tc.env, seed=tc.seed + state["timesteps"])
    if resume:
        venv = VecNormalize.load(str(run_dir / "latest.vecnorm.pkl"), fast)
        model = PPO.load(run_dir / "latest.zip", env=venv, device="cpu")
    else:
        venv = init_normalization(VecNormalize(fast, norm_obs=True, norm_reward=False, gamma=tc.gamma), tc)
        model = PPO("MlpPolicy", venv, seed=tc.seed, device="cpu", verbose=0, **_ppo_kwargs(tc))
        init_weights(model, Path(tc.init_from), tc.init_std, VIEWS[tc.env.lidar], tc.env.obs_stride)
    try:
        return imitate(model, venv, tc, run_dir, state, total, progress=progress)
    except ValueError as e:  # a teacher that cannot label this env (training/teacher.py)
        print(f"racecav train dagger: {e}")
        return 2


def init_normalization(venv, tc):
    """Start a new run's VecNormalize ``venv`` from the statistics beside ``tc.init_from`` (if
    any): the weights expect the statistics they were trained with; a 1-scan policy's serve every
    scan of a stack."""
    init_norm = Path(tc.init_from).with_suffix(".vecnorm.pkl") if tc.init_from else None
    if init_norm is None or not init_norm.is_file():
        return venv
    with init_norm.open("rb") as f:
        old = pickle.load(f)
    src_view, view = source_view(Path(tc.init_from)), VIEWS[tc.env.lidar]
    venv.ret_rms = old.ret_rms
    venv.obs_rms.mean, venv.obs_rms.var = (
        map_inputs(a, src_view, view, tc.env.obs_stack, stats=True)
        for a in (old.obs_rms.mean, old.obs_rms.var))
    # a new view's outer rays start from the nearest old ray's statistics: a smaller count lets
    # them adapt within ~1 M samples
    venv.obs_rms.count = old.obs_rms.count if src_view == view else min(old.obs_rms.count, 1e5)
    return venv


def source_view(path: Path):
    """The lidar view a policy zip was trained on (the paper's unless it says otherwise)."""
    return VIEWS[source_env(path, "lidar", "paper")]


def restride(w, n_rays: int, k: float):
    """First-layer weights (out, S * R) of a stack trained with scans ``s`` periods apart, for
    scans ``k * s`` apart. Each older scan is read as a linear interpolation between the newest
    and the farther one (s_old ~ (1 - 1/k) s_new + s_far / k), so the model starts with the old
    response to motion, then learns from the longer baseline."""
    import numpy as np

    w = np.array(w, dtype=np.float64)
    for j in range(1, w.shape[1] // n_rays):
        old = w[:, j * n_rays:(j + 1) * n_rays].copy()
        w[:, :n_rays] += old * (1.0 - 1.0 / k)
        w[:, j * n_rays:(j + 1) * n_rays] = old / k
    return w


def map_inputs(w, src, dst, n_stack: int, stats: bool = False):
    """Input-side arrays of a policy trained on view ``src`` for a model on view ``dst`` with
    ``n_stack`` scans: first-layer weights (out, S_src * R_src) or VecNormalize statistics
    (stats=True, shape (S_src * R_src,)).

    Weights: source ray i adds into the destination ray nearest in angle (two rays that fall
    on one wider-spaced ray add up, as they saw nearly the same range); destination rays outside
    the source view and extra scan slots get zero, so the model starts with the old behaviour.
    Statistics: each destination ray takes its nearest source ray's, extra slots the last slot's.
    """
    import numpy as np

    def angles(v):  # float64 (ray_angles is float32: too coarse to break ties consistently)
        return v.angle_min + v.angle_increment * np.arange(v.n_rays)

    a_src, a_dst = angles(src), angles(dst)
    w = np.asarray(w)
    w2 = w[None] if stats else w
    r_src, r_dst = len(a_src), len(a_dst)
    s_src = w2.shape[1] // r_src
    out = np.zeros((w2.shape[0], n_stack * r_dst), dtype=w2.dtype)

    def nearest(a, view):  # ray of ``view`` nearest to angles a; a tie (half-way) goes to the lower
        return np.ceil((a - view.angle_min) / view.angle_increment - 0.5 - 1e-3).astype(np.int64)

    if stats:
        near = np.clip(nearest(a_dst, src), 0, r_src - 1)  # per destination ray
    else:
        near = nearest(a_src, dst)  # per source ray
        inside = (near >= 0) & (near < r_dst)
        near = np.clip(near, 0, r_dst - 1)
    for k in range(n_stack):
        if k >= s_src and not stats:
            break
        block = w2[:, min(k, s_src - 1) * r_src:(min(k, s_src - 1) + 1) * r_src]
        dst_block = out[:, k * r_dst:(k + 1) * r_dst]
        if stats:
            dst_block[:] = block[:, near]
        else:
            np.add.at(dst_block.T, near[inside], block.T[inside])
    return out[0] if stats else out


def init_weights(model, path: Path, std: float | None = None, view=None, stride: int = 1) -> None:
    """Start ``model``'s policy from an SB3 zip. A first layer for other inputs (a 1-scan policy
    into a stacked observation, the paper's view into a wider one, a stack with another stride)
    is mapped by map_inputs and restride, so the new model starts with the old behaviour.
    ``std``: reset the action std to this. ``view``: the model's lidar view (default the
    paper's); ``stride``: its scan periods between stacked scans."""
    import numpy as np
    import torch
    from stable_baselines3 import PPO

    view = view or VIEWS["paper"]
    src_view = source_view(path)
    src = PPO.load(path, device="cpu").policy.state_dict()
    dst = model.policy.state_dict()
    n_stack = dst["mlp_extractor.policy_net.0.weight"].shape[1] // view.n_rays
    width = dst["mlp_extractor.policy_net.0.weight"].shape[0]
    if src["mlp_extractor.policy_net.0.weight"].shape[0] != width:
        raise ValueError(f"--init-from {path}: {src['mlp_extractor.policy_net.0.weight'].shape[0]} hidden units, "
                         f"the model {width} (--hidden)")
    for k, v in src.items():
        if k == "log_std":  # below: its shape differs with gSDE
            continue
        if k in dst and (dst[k].shape != v.shape or (k.endswith("net.0.weight") and src_view != view)):
            if k.endswith("net.0.weight") and v.shape[1] % src_view.n_rays == 0:
                src[k] = torch.as_tensor(map_inputs(v.numpy(), src_view, view, n_stack))
            if src[k].shape != dst[k].shape:
                raise ValueError(f"--init-from {path}: {k} has shape {tuple(v.shape)}, the model {tuple(dst[k].shape)}")
    src_stride = int(source_env(path, "obs_stride", 1))
    if src_stride != stride:
        for k in [k for k in src if k.endswith("net.0.weight")]:
            src[k] = torch.as_tensor(restride(src[k].numpy(), view.n_rays, stride / src_stride), dtype=src[k].dtype)
    if std is not None:
        src["log_std"] = torch.full_like(src["log_std"], float(np.log(std)))
    if src["log_std"].shape != dst["log_std"].shape:  # one of the two explores with gSDE
        if dst["log_std"].dim() == 1 and std is None:
            raise ValueError(f"--init-from {path}: a gSDE policy into one without: give its noise with --init-std")
        src["log_std"] = (dst["log_std"] if dst["log_std"].dim() == 2  # calibrated by calibrate_sde
                          else torch.full_like(dst["log_std"], float(np.log(std))))
    model.policy.load_state_dict(src, strict=True)


def source_std(path: Path):
    """The action std (per action) of the SB3 zip ``path``; None for a gSDE policy (its std
    depends on the state)."""
    import torch
    from stable_baselines3 import PPO

    log_std = PPO.load(path, device="cpu").policy.state_dict()["log_std"]
    return torch.exp(log_std).numpy() if log_std.dim() == 1 else None


def calibrate_sde(model, obs, std) -> None:
    """Set a gSDE policy's noise weights so that its action std, averaged over the normalised
    observations ``obs``, is ``std`` (a number, or one per action): the noise of the action ``a``
    has the variance ``sum_j latent_j^2 sigma_ja^2`` over the last hidden layer's ``latent``."""
    import numpy as np
    import torch

    policy = model.policy
    with torch.no_grad():
        feats = policy.extract_features(torch.as_tensor(obs, dtype=torch.float32), policy.pi_features_extractor)
        latent_sq = float((policy.mlp_extractor.forward_actor(feats) ** 2).sum(1).mean())
        sigma = torch.as_tensor(np.broadcast_to(np.asarray(std, np.float32), (policy.log_std.shape[1],)).copy())
        policy.log_std.copy_(torch.log(sigma / np.sqrt(latent_sq)).expand_as(policy.log_std))
    policy.reset_noise(model.n_envs)


def action_std(policy, obs) -> float:
    """The action std that progress.csv's std column reports: the std of each action, RMS over the
    normalised observations ``obs`` (with gSDE it depends on the observation; without, it does
    not), averaged over the actions. SB3's own ``train/std`` is the noise weights' mean under
    gSDE, which is not an action std."""
    import torch

    with torch.no_grad():
        std = policy.get_distribution(torch.as_tensor(obs, dtype=torch.float32)).distribution.stddev
    return float(std.pow(2).mean(0).sqrt().mean())


def _configure_logger(model, run_dir: Path) -> None:
    """SB3 logger: our CSV (appending across resumes) + TensorBoard if installed."""
    from stable_baselines3.common.logger import Logger

    formats = [_csv_writer(run_dir / "progress.csv")]
    try:
        import tensorboard  # noqa: F401
        from stable_baselines3.common.logger import TensorBoardOutputFormat

        formats.append(TensorBoardOutputFormat(str(run_dir / "tb")))
    except ImportError:
        pass
    model.set_logger(Logger(str(run_dir), formats))


_CSV_CLASS = None


def _csv_writer(path: Path):
    """SB3 KVWriter appending a fixed set of columns to progress.csv (resumable).

    SB3's on-policy loop dumps the log after each rollout and before that rollout's update, so
    the train/* values of a dump are the previous update's. A row is therefore written one dump
    late, with the train/* values of the update on its own rollout; ``flush`` writes the last one
    with the values the logger holds when learning ends (its update, if it ran)."""
    global _CSV_CLASS
    if _CSV_CLASS is None:
        from stable_baselines3.common.logger import KVWriter

        class _CsvAppend(KVWriter):
            def __init__(self, path: Path):
                self.path = path
                self.extra: dict = {}
                self.pending: dict | None = None  # the newest rollout's row, waiting for its update

            @staticmethod
            def _fields(key_values, train: bool) -> dict:
                return {k.split("/")[-1]: v for k, v in key_values.items()
                        if k.startswith("train/") == train and k.split("/")[-1] in CSV_FIELDS}

            def _emit(self, train: dict) -> None:
                row, self.pending = self.pending, None
                if row is None:
                    return
                row.update({k: v for k, v in train.items() if k not in row})  # extra's std stays
                new = not self.path.is_file() or self.path.stat().st_size == 0
                with self.path.open("a", newline="") as f:
                    w = csv.DictWriter(f, CSV_FIELDS, extrasaction="ignore")
                    if new:
                        w.writeheader()
                    w.writerow(row)

            def write(self, key_values, key_excluded, step=0):
                self._emit(self._fields(key_values, train=True))
                row = {"timesteps": key_values.get("time/total_timesteps", step), **self.extra}
                row.update({k: v for k, v in self._fields(key_values, train=False).items() if k not in row})
                self.pending = row

            def flush(self, key_values) -> None:
                """Write the pending row with the train/* values in ``key_values`` (the logger's
                values after the last update, not dumped by SB3)."""
                self._emit(self._fields(key_values, train=True))

            def close(self):
                pass

        _CSV_CLASS = _CsvAppend
    return _CSV_CLASS(path)


def _make_callback_class():
    from stable_baselines3.common.callbacks import BaseCallback

    class _TrainCallback(BaseCallback):
        """Progress bar, CSV extras, periodic and on-signal checkpoints."""

        def __init__(self, run_dir: Path, total: int, every: int, wall0: float, progress: bool = True):
            super().__init__()
            self.run_dir, self.total, self.every = run_dir, total, max(1, int(every))
            self.wall0 = wall0
            self.t_start = time.monotonic()
            self.stop_requested = False
            self.progress = progress
            self.bar = None
            self.rollout_start_steps = 0
            self.episodes = 0
            self._rate_t, self._rate_n = time.monotonic(), 0

        def request_stop(self, signum, frame):  # signal handler: stop at the next env step
            log.warning("signal %d: checkpoint and stop", signum)
            self.stop_requested = True

        def wall(self) -> float:
            return self.wall0 + time.monotonic() - self.t_start

        def _on_training_start(self) -> None:
            self.next_ckpt = (self.model.num_timesteps // self.every + 1) * self.every
            self._rate_n = self.model.num_timesteps
            if self.progress:
                from tqdm import tqdm

                self.bar = tqdm(total=self.total, initial=self.model.num_timesteps, unit="sa",
                                unit_scale=True, mininterval=2.0, smoothing=0.05,
                                dynamic_ncols=True, desc=self.run_dir.name)

        def _on_rollout_start(self) -> None:
            # After the previous update: weights, optimizer and step count belong together here.
            if self.model.num_timesteps >= self.next_ckpt:
                self.save(self.model)
                self.next_ckpt = (self.model.num_timesteps // self.every + 1) * self.every
            self.rollout_start_steps = self.model.num_timesteps

        def _on_step(self) -> bool:
            if self.bar is not None:
                self.bar.update(self.training_env.num_envs)
            self.episodes += int(self.locals["dones"].sum())
            return not self.stop_requested

        def _on_rollout_end(self) -> None:
            now = time.monotonic()
            rate = (self.model.num_timesteps - self._rate_n) / max(now - self._rate_t, 1e-9)
            self._rate_t, self._rate_n = now, self.model.num_timesteps
            buf = self.model.ep_info_buffer
            ep = float(sum(e["r"] for e in buf) / len(buf)) if buf else float("nan")
            extra = {"wall_s": round(self.wall(), 2), "samples_per_s": round(rate, 1), "ep_count": self.episodes}
            if self.model.use_sde:  # the policy's action std on this rollout (before its update)
                obs = self.model.rollout_buffer.observations
                obs = obs.reshape(-1, obs.shape[-1])
                extra["std"] = round(action_std(self.model.policy, obs[:: max(1, len(obs) // 1024)]), 5)
            for fmt in self.model.logger.output_formats:
                if isinstance(fmt, _CSV_CLASS):
                    fmt.extra = extra
            self.episodes = 0
            self._log_curriculum()
            if self.bar is not None:
                self.bar.set_postfix_str(f"ep_return {ep:.1f}", refresh=False)

        def _log_curriculum(self) -> None:
            """curriculum.csv: each family's training success rate (the draw weights' input)."""
            cur = getattr(self.training_env.unwrapped, "curriculum", None)
            if cur is None:
                return
            path = self.run_dir / "curriculum.csv"
            new = not path.is_file()
            with path.open("a", newline="") as f:
                w = csv.writer(f)
                if new:
                    w.writerow(["timesteps", *cur.names])
                w.writerow([self.model.num_timesteps, *(f"{r:.3f}" for r in cur.success_rates().values())])

        def save(self, model, final: bool = False) -> Path:
            return save_checkpoint(self.run_dir, model, model.get_vec_normalize_env(), self.wall(), final)

        def close(self) -> None:
            if self.bar is not None:
                self.bar.close()
            if getattr(self, "model", None) is not None:  # progress.csv's last row, with its update's values
                for fmt in self.model.logger.output_formats:
                    if isinstance(fmt, _CSV_CLASS):
                        fmt.flush(self.model.logger.name_to_value)

    return _TrainCallback


def limit_blas_threads(n: int = 1) -> bool:
    """Pin OpenBLAS (numpy's matmul) to ``n`` threads in this process, after numpy is imported.

    On 2 shared cores OpenBLAS's own threads make the batched traffic policy (960 x 170 @ 170 x 64)
    20x slower (13 ms instead of 0.55 ms, measured); OPENBLAS_NUM_THREADS only works before numpy
    loads, and the CLI has loaded it by then.
    """
    import ctypes

    try:
        libs = {line.split()[-1] for line in open("/proc/self/maps") if "openblas" in line.lower()}
    except OSError:
        return False
    for path in libs:
        lib = ctypes.CDLL(path)
        for fn in ("scipy_openblas_set_num_threads64_", "openblas_set_num_threads64_",
                   "openblas_set_num_threads"):
            if hasattr(lib, fn):
                getattr(lib, fn)(ctypes.c_int(n))
                return True
    return False
