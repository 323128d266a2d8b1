"""``racecav train``: PPO training of the racing and overtaking policies, resumable.

    racecav train racing   [--steps N] [--run-dir DIR] [--resume] [--preset paper|fast] [...]
    racecav train overtake --heading default|reversed [--driver policy:racing] [...]
    racecav train select   --run-dir DIR [--trials N]      (training/select.py)
    racecav train ship     --run-dir DIR --checkpoint STEP --name racing|default|reversed
    racecav train report                                   (docs/training.md)

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

import argparse
import csv
import json
import logging
import pickle
import os
import signal
import subprocess
import time
from pathlib import Path

log = logging.getLogger("racecav.train")

PRESETS: dict[str, dict] = {
    # The paper's PPO setting (section 3.3); SB3 defaults for the rest.
    "paper": dict(n_envs=1, n_steps=2048, batch_size=64, n_epochs=10, gamma=0.99,
                  learning_rate=3e-4, gae_lambda=0.95, clip_range=0.2, ent_coef=0.0,
                  vf_coef=0.5, max_grad_norm=0.5, normalize=False, checkpoint_every=5_000_000),
    # Chosen by measurement for 2 shared CPU cores (docs/training.md): same rollout length per
    # env-step of experience, 64 envs per rollout, minibatch 2048, 10 epochs.
    "fast": dict(n_envs=64, n_steps=128, batch_size=2048, n_epochs=10, gamma=0.99,
                 learning_rate=3e-4, gae_lambda=0.95, clip_range=0.2, ent_coef=0.0,
                 vf_coef=0.5, max_grad_norm=0.5, normalize=True, checkpoint_every=1_000_000),
}
SETTINGS = list(PRESETS["paper"])
CSV_FIELDS = ["timesteps", "wall_s", "samples_per_s", "ep_rew_mean", "ep_len_mean", "ep_count",
              "approx_kl", "clip_fraction", "entropy_loss", "value_loss", "policy_gradient_loss",
              "explained_variance", "std", "learning_rate"]
RUNS_DIR = Path("runs")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="train_cmd", required=True, metavar="STAGE")
    for stage, help_ in (("racing", "stage 1: the racing policy on the empty track (0 obstacles)"),
                         ("overtake", "stage 2: overtaking with 15 obstacle cars driven by the racing policy")):
        p = sub.add_parser(stage, help=help_, description=help_)
        p.add_argument("--heading", choices=["default", "reversed"], default="default")
        p.add_argument("--steps", type=float, default=1e6, help="total samples of the run (default 1e6)")
        p.add_argument("--run-dir", type=Path, help="run folder (default runs/<stage>[-<heading>])")
        p.add_argument("--resume", action="store_true", help="continue the run in --run-dir from latest")
        p.add_argument("--preset", choices=list(PRESETS), default="paper")
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--n-envs", type=int)
        p.add_argument("--n-steps", type=int, help="rollout steps per env (PPO n_steps)")
        p.add_argument("--batch-size", type=int)
        p.add_argument("--n-epochs", type=int)
        p.add_argument("--gamma", type=float)
        p.add_argument("--learning-rate", "--lr", dest="learning_rate", type=float)
        p.add_argument("--gae-lambda", type=float)
        p.add_argument("--clip-range", type=float)
        p.add_argument("--ent-coef", type=float)
        p.add_argument("--vf-coef", type=float)
        p.add_argument("--max-grad-norm", type=float)
        p.add_argument("--normalize", action=argparse.BooleanOptionalAction, default=None,
                       help="VecNormalize observations and rewards (shipped with the weights)")
        p.add_argument("--checkpoint-every", type=float, help="samples between checkpoints")
        p.add_argument("--n-obstacles", type=int, help="default: 0 racing, 15 overtake")
        p.add_argument("--driver", help="traffic driver: centerline | policy:PATH|NAME "
                                        "(overtake default: policy:racing)")
        p.add_argument("--time-limit", type=float, help="episode time limit (s)")
        p.add_argument("--world", help="training world (common/data/worlds; default racetrack)")
        p.add_argument("--scenarios", help="scenario episodes: a conflict suite (NAME or DIR; its train "
                       "split), a folder of scenario files, or one file")
        p.add_argument("--scenario-share", type=float, help="share of the batch running scenario "
                       "episodes (default 0.5 with --scenarios)")
        p.add_argument("--obs-stack", type=int, help="scans per observation, newest first (default 1: the "
                       "paper's; > 1 shows motion; --init-from a 1-scan policy starts with zero weights on the "
                       "older scans, i.e. the same behaviour)")
        p.add_argument("--contact-penalty", type=float, help="reward at a contact (<= 0; default 0: "
                       "the paper's reward)")
        p.add_argument("--init-from", type=Path, help="start the weights (and, if a .vecnorm.pkl "
                                                       "lies beside it, the normalisation) from this SB3 zip")
        p.add_argument("--no-progress", action="store_true", help="no tqdm bar")
        p.set_defaults(stage=stage)
    from racecav.training import select  # cheap module: argument definitions only

    select.add_subcommands(sub)
    p = sub.add_parser("export", help="write a policy as ONNX: DIR/model.onnx + model.json (ray layout, "
                       "normalisation, action meaning); run it with racecav policy --backend onnxruntime")
    p.add_argument("--onnx", required=True, metavar="NAME", help="racing | default | reversed | PATH to a policy .npz")
    p.add_argument("--out", type=Path, help="output folder (default runs/onnx/NAME)")
    p.add_argument("--car", default="slash", help="car file (lidar layout, steering mapping in the sidecar)")
    p.set_defaults(stage="export")


def run(args, cfg) -> int:
    if args.train_cmd in ("racing", "overtake"):
        return train(args, cfg)
    if args.train_cmd == "export":
        return export_onnx(args)
    from racecav.training import select

    return select.run(args, cfg)


def export_onnx(args) -> int:
    """``racecav train export --onnx NAME``: services/policy/onnx_export.py does the work."""
    try:
        from racecav.services.policy.onnx_export import export
    except ImportError as e:
        print(f"racecav train export: {e} (pip install 'racecav[onnx]')")
        return 2
    out = args.out or RUNS_DIR / "onnx" / Path(args.onnx).stem
    try:
        model, meta = export(args.onnx, out, args.car)
    except ImportError as e:
        print(f"racecav train export: {e} (pip install 'racecav[onnx]')")
        return 2
    except (ValueError, FileNotFoundError) as e:
        print(f"racecav train export: {e}")
        return 2
    print(f"wrote {model} and {meta}")
    return 0


# ----------------------------------------------------------------------------------- settings
def run_settings(args) -> dict:
    """All settings of a run: the preset, overridden by explicit flags."""
    s = dict(PRESETS[args.preset])
    for k in SETTINGS:
        v = getattr(args, k, None)
        if v is not None:
            s[k] = v
    s["checkpoint_every"] = int(s["checkpoint_every"])
    overtake = args.stage == "overtake"
    s.update(stage=args.stage, preset=args.preset, seed=args.seed,
             heading=args.heading if overtake else "default",
             n_obstacles=args.n_obstacles if args.n_obstacles is not None else (15 if overtake else 0),
             driver=args.driver or ("policy:racing" if overtake else "centerline"),
             time_limit=args.time_limit, world=args.world or "racetrack",
             init_from=str(args.init_from) if args.init_from else None,
             scenarios=args.scenarios,
             scenario_share=(args.scenario_share if args.scenario_share is not None
                             else (0.5 if args.scenarios else 0.0)),
             contact_penalty=args.contact_penalty or 0.0,
             obs_stack=args.obs_stack or 1)
    return s


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent, timeout=5).stdout.strip()
    except Exception:  # noqa: BLE001 - metadata only
        return ""


def make_venv(s: dict, seed: int, cfg=None):
    """The (VecMonitor-wrapped) FastVecEnv of a run's settings."""
    from stable_baselines3.common.vec_env import VecMonitor

    from racecav.training.vec_env import FastVecEnv

    venv = FastVecEnv(n_envs=s["n_envs"], config=cfg.env if cfg is not None else None,
                      heading=s["heading"], n_obstacles=s["n_obstacles"], driver=s["driver"],
                      time_limit=s["time_limit"], world=s.get("world", "racetrack"),
                      scenarios=s.get("scenarios"), scenario_share=s.get("scenario_share", 0.0),
                      contact_penalty=s.get("contact_penalty", 0.0), obs_stack=s.get("obs_stack", 1),
                      seed=seed)
    return VecMonitor(venv)


def _ppo_kwargs(s: dict) -> dict:
    import torch

    return dict(n_steps=s["n_steps"], batch_size=s["batch_size"], n_epochs=s["n_epochs"],
                gamma=s["gamma"], learning_rate=s["learning_rate"], gae_lambda=s["gae_lambda"],
                clip_range=s["clip_range"], ent_coef=s["ent_coef"], vf_coef=s["vf_coef"],
                max_grad_norm=s["max_grad_norm"],
                policy_kwargs=dict(net_arch=[64, 64], activation_fn=torch.nn.Tanh))


# ----------------------------------------------------------------------------------- training
def train(args, cfg) -> int:
    import numpy as np
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    torch.set_num_threads(1)
    limit_blas_threads(1)
    run_dir = args.run_dir or RUNS_DIR / (args.stage if args.stage == "racing" else f"overtake-{args.heading}")
    run_dir = Path(run_dir)
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    cfg_path = run_dir / "config.json"
    total = int(args.steps)
    if args.resume:
        if not (run_dir / "latest.zip").is_file():
            log.error("--resume: no %s", run_dir / "latest.zip")
            return 2
        s = json.loads(cfg_path.read_text())
        state = json.loads((run_dir / "latest.json").read_text())
    else:
        if (run_dir / "latest.zip").exists():
            log.error("%s already holds a run: use --resume or another --run-dir", run_dir)
            return 2
        s = run_settings(args)
        s["git_commit"] = git_commit()
        s["started"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        cfg_path.write_text(json.dumps(s, indent=2) + "\n")
        state = {"timesteps": 0, "wall_s": 0.0}
    s["total_steps"] = total

    # Env seed: the run's seed, shifted on resume so a resumed run does not replay its episodes.
    venv = make_venv(s, seed=s["seed"] + state["timesteps"], cfg=cfg)
    if s["normalize"]:
        if args.resume:
            venv = VecNormalize.load(str(run_dir / "latest.vecnorm.pkl"), venv)
            venv.training = True
        else:
            venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=s["gamma"])
            init_norm = Path(s["init_from"]).with_suffix(".vecnorm.pkl") if s.get("init_from") else None
            if init_norm is not None and init_norm.is_file():
                # the weights expect the statistics they were trained with: start from those
                with init_norm.open("rb") as f:
                    old = pickle.load(f)
                venv.ret_rms = old.ret_rms
                k = s.get("obs_stack", 1)  # a 1-scan policy's statistics for every scan of the stack
                venv.obs_rms.mean = np.tile(old.obs_rms.mean, k // max(1, len(old.obs_rms.mean) // 170))
                venv.obs_rms.var = np.tile(old.obs_rms.var, k // max(1, len(old.obs_rms.var) // 170))
                venv.obs_rms.count = old.obs_rms.count
    if args.resume:
        model = PPO.load(run_dir / "latest.zip", env=venv, device="cpu")
        _truncate_csv(run_dir / "progress.csv", model.num_timesteps)
        log.info("resumed %s at %d samples", run_dir, model.num_timesteps)
    else:
        model = PPO("MlpPolicy", venv, seed=s["seed"], device="cpu", verbose=0, **_ppo_kwargs(s))
        if s.get("init_from"):
            init_weights(model, Path(s["init_from"]))
    _configure_logger(model, run_dir)
    cb = _make_callback_class()(run_dir, total, s["checkpoint_every"], state["wall_s"], progress=not args.no_progress)
    remaining = total - model.num_timesteps
    if remaining <= 0:
        log.info("run already at %d >= %d samples", model.num_timesteps, total)
        return 0
    old = {sig: signal.signal(sig, cb.request_stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        model.learn(remaining, callback=cb, reset_num_timesteps=False, progress_bar=False)
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


def init_weights(model, path: Path) -> None:
    """Start ``model``'s policy from an SB3 zip. A first layer narrower than the model's (a
    1-scan policy into a stacked observation) is widened with zero weights on the extra inputs,
    so the new model starts with the old behaviour."""
    import torch
    from stable_baselines3 import PPO

    src = PPO.load(path, device="cpu").policy.state_dict()
    dst = model.policy.state_dict()
    for k, v in src.items():
        if k in dst and dst[k].shape != v.shape:
            if v.ndim == 2 and dst[k].shape[0] == v.shape[0] and dst[k].shape[1] % v.shape[1] == 0:
                w = torch.zeros_like(dst[k])
                w[:, : v.shape[1]] = v
                src[k] = w
            else:
                raise ValueError(f"--init-from {path}: {k} has shape {tuple(v.shape)}, the model {tuple(dst[k].shape)}")
    model.policy.load_state_dict(src, strict=True)


def _truncate_csv(path: Path, timesteps: int) -> None:
    """Drop learning-curve rows written after the checkpoint being resumed."""
    if not path.is_file():
        return
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if int(float(r["timesteps"])) <= timesteps]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, CSV_FIELDS)
        w.writeheader()
        w.writerows(rows)


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
    """SB3 KVWriter appending a fixed set of columns to progress.csv (resumable)."""
    global _CSV_CLASS
    if _CSV_CLASS is None:
        from stable_baselines3.common.logger import KVWriter

        class _CsvAppend(KVWriter):
            def __init__(self, path: Path):
                self.path = path
                self.extra: dict = {}

            def write(self, key_values, key_excluded, step=0):
                new = not self.path.is_file() or self.path.stat().st_size == 0
                row = {"timesteps": key_values.get("time/total_timesteps", step)}
                row.update(self.extra)
                for k, v in key_values.items():
                    name = k.split("/")[-1]
                    if name in CSV_FIELDS and name not in row:
                        row[name] = v
                with self.path.open("a", newline="") as f:
                    w = csv.DictWriter(f, CSV_FIELDS, extrasaction="ignore")
                    if new:
                        w.writeheader()
                    w.writerow(row)

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
            for fmt in self.model.logger.output_formats:
                if isinstance(fmt, _CSV_CLASS):
                    fmt.extra = {"wall_s": round(self.wall(), 2), "samples_per_s": round(rate, 1),
                                 "ep_count": self.episodes}
            self.episodes = 0
            if self.bar is not None:
                self.bar.set_postfix_str(f"ep_return {ep:.1f}", refresh=False)

        def save(self, model, final: bool = False) -> Path:
            n = model.num_timesteps
            ck = self.run_dir / "checkpoints" / f"step_{n:09d}"
            model.save(ck.with_suffix(".zip"))
            vn = model.get_vec_normalize_env()
            if vn is not None:
                vn.save(str(ck.with_suffix(".vecnorm.pkl")))
            # latest: copies written then renamed, so an interruption never leaves half a file
            for suffix in (".zip", ".vecnorm.pkl"):
                src = ck.with_suffix(suffix)
                if src.is_file():
                    tmp = self.run_dir / f"latest.tmp{suffix}"
                    tmp.write_bytes(src.read_bytes())
                    os.replace(tmp, self.run_dir / f"latest{suffix}")
            state = {"timesteps": n, "wall_s": round(self.wall(), 2), "checkpoint": ck.name,
                     "final": final, "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
            (self.run_dir / "latest.tmp.json").write_text(json.dumps(state) + "\n")
            os.replace(self.run_dir / "latest.tmp.json", self.run_dir / "latest.json")
            log.info("checkpoint %s (%.0f s wall)", ck.name, self.wall())
            return ck

        def close(self) -> None:
            if self.bar is not None:
                self.bar.close()

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
