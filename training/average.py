"""``racecav train average``: a run's checkpoints averaged over a sliding window (SWA, Izmailov et
al. 2018: the mean of the weights along one run's path lies nearer the middle of the optimum's
basin than any single iterate).

For each checkpoint of ``--run-dir`` with ``window - 1`` checkpoints before it, the element-wise
mean of the ``window`` policies' parameters (actor, critic and action noise) is written as the
same step in ``--out``, with the pooled observation normalisation of the same checkpoints (the
mean of their means; their mean variance plus the variance of their means). ``--out`` gets the
source's config.json, so ``racecav train select --run-dir OUT`` evaluates the averages exactly as
it evaluates the run, checkpoint for checkpoint, and ``averaged.json`` names the sources of each.
Averages are only meaningful along one run (checkpoints of the same lineage and architecture).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path


def add_subcommands(sub) -> None:
    p = sub.add_parser("average", help="a run's checkpoints averaged over a sliding window of checkpoints (SWA) "
                       "-> a run folder that `train select` evaluates like the run")
    p.add_argument("--run-dir", type=Path, required=True, help="the run whose checkpoints/step_N.zip are averaged")
    p.add_argument("--window", type=int, default=4, help="checkpoints per average (the newest and the ones before it)")
    p.add_argument("--out", type=Path, help="output run folder (default: <run>-avg<window> beside the run)")
    p.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    p.set_defaults(stage="average")


def average_states(states: list[dict]) -> dict:
    """Element-wise mean of SB3 policy state dicts (float64 accumulation, each tensor's dtype kept).

    :raises ValueError: for no states, or states of different keys or shapes (another architecture).
    """
    import torch

    if not states:
        raise ValueError("average: no checkpoints to average")
    keys = list(states[0])
    for s in states[1:]:
        if list(s) != keys or any(s[k].shape != states[0][k].shape for k in keys):
            raise ValueError("average: checkpoints of different architectures (keys or shapes differ)")
    out = {}
    for k in keys:
        if states[0][k].is_floating_point():
            out[k] = (torch.stack([s[k].double() for s in states]).mean(0)).to(states[0][k].dtype)
        else:  # integer buffers (none in an MlpPolicy today): the newest
            out[k] = states[-1][k].clone()
    return out


def pooled_moments(means: list, variances: list) -> tuple:
    """Mean and variance of an equal mixture of the given distributions' moments."""
    import numpy as np

    m, v = np.stack(means), np.stack(variances)
    return m.mean(0), v.mean(0) + m.var(0)


def _load_norm(path: Path):
    import pickle

    with path.open("rb") as f:
        return pickle.load(f)


def _save_norm(norm, path: Path) -> None:
    import pickle

    # VecNormalize.__getstate__ deletes the attributes an unpickled object lacks (its env's)
    norm.__dict__.setdefault("class_attributes", None)
    norm.__dict__.setdefault("returns", None)
    with path.open("wb") as f:
        pickle.dump(norm, f)


def average_run(run_dir: Path, window: int, out: Path, progress: bool = True) -> list[Path]:
    """Write ``out``'s averaged checkpoints (one per source checkpoint with a full window).

    :raises ValueError: for a window < 1 or a run with fewer checkpoints than the window.
    :raises FileNotFoundError: for a folder without config.json.
    """
    import torch
    from stable_baselines3 import PPO
    from tqdm import tqdm

    from racecav.training.select import _checkpoints, _step

    if window < 1:
        raise ValueError(f"--window {window}: must be >= 1")
    if not (run_dir / "config.json").is_file():
        raise FileNotFoundError(f"{run_dir}: no config.json (not a run folder)")
    cks = _checkpoints(run_dir)
    if len(cks) < window:
        raise ValueError(f"{run_dir}: {len(cks)} checkpoints, fewer than --window {window}")
    if out.resolve() == run_dir.resolve():
        raise ValueError("--out: must not be the source run's folder")
    torch.set_num_threads(1)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    shutil.copy(run_dir / "config.json", out / "config.json")
    states = {}  # checkpoint -> policy state dict, only the current window's
    sources, written = {}, []
    for i in tqdm(range(window - 1, len(cks)), desc=f"average {run_dir.name}", unit="ckpt", disable=not progress):
        win = cks[i - window + 1:i + 1]
        states = {p: states.get(p) or PPO.load(p, device="cpu").policy.state_dict() for p in win}
        model = PPO.load(win[-1], device="cpu")
        model.policy.load_state_dict(average_states([states[p] for p in win]))
        dst = out / "checkpoints" / win[-1].name
        model.save(dst)
        vn = [p.with_suffix(".vecnorm.pkl") for p in win]
        if all(v.is_file() for v in vn):
            norms = [_load_norm(v) for v in vn]
            newest = norms[-1]
            newest.obs_rms.mean, newest.obs_rms.var = pooled_moments([n.obs_rms.mean for n in norms],
                                                                     [n.obs_rms.var for n in norms])
            _save_norm(newest, dst.with_suffix(".vecnorm.pkl"))
        elif any(v.is_file() for v in vn):
            raise ValueError(f"{run_dir}: some checkpoints of {[p.name for p in win]} lack their .vecnorm.pkl")
        sources[str(_step(win[-1]))] = [_step(p) for p in win]
        written.append(dst)
    (out / "averaged.json").write_text(json.dumps({"source": str(run_dir), "window": window,
                                                   "checkpoints": sources}, indent=2) + "\n")
    return written


def run(args, cfg) -> int:
    out = args.out or args.run_dir.parent / f"{args.run_dir.name}-avg{args.window}"
    try:
        written = average_run(args.run_dir, args.window, out, progress=not args.no_progress)
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"racecav train average: {e}") from None
    print(f"wrote {len(written)} averaged checkpoints to {out / 'checkpoints'}; evaluate them with "
          f"`racecav train select --run-dir {out}`")
    return 0
