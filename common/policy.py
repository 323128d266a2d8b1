"""The shipped policy format and its plain-numpy inference (no torch or SB3 at import time).

A policy is two files side by side:

- ``<name>.npz``: float32 arrays ``w0 (170, 64)``, ``b0 (64,)``, ``w1 (64, 64)``, ``b1 (64,)``,
  ``w2 (64, 2)``, ``b2 (2,)`` (the actor of SB3's MlpPolicy, net_arch [64, 64], tanh: action
  mean = w2^T tanh(w1^T tanh(w0^T x + b0) + b1) + b2), ``log_std (2,)`` (kept for reference; the
  deterministic action is the mean), and, when training normalised observations (SB3
  VecNormalize), ``obs_mean (170,)``, ``obs_var (170,)``, ``obs_clip ()``, ``obs_eps ()``.
- ``<name>.json``: metadata (training steps, seed, settings, git commit, evaluation results ...).

Observation contract: the input is the sanitised scan (``racecav.common.lidar.sanitize``: 170
finite ranges in [range_min, range_max]); normalisation, if any, is part of the policy and is
applied here: ``x = clip((obs - obs_mean) / sqrt(obs_var + obs_eps), -obs_clip, obs_clip)``.
The action is the Gaussian mean clipped to [-1, 1] (what SB3's ``predict(deterministic=True)``
returns), ``[a_T, a_delta]``.

``load_policy("racing" | "default" | "reversed" | PATH)``; ``export_policy(sb3_model, path,
metadata, obs_rms=None)`` writes both files from a trained SB3 PPO model.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

MODELS_DIR = Path(__file__).resolve().parent / "data" / "policies"
"""Shipped policies: ``MODELS_DIR/<name>.npz`` + ``.json`` (+ the SB3 ``.zip``)."""
SHIPPED = ("racing", "default", "reversed", "avoid", "avoid-paper")
_LAYERS = ("w0", "b0", "w1", "b1", "w2", "b2")


class NumpyPolicy:
    """The deterministic actor as float32 numpy: ``policy(obs) -> action``.

    :param arrays: the npz contents (see the module docstring).
    :param metadata: the JSON metadata (free-form dict).
    """

    def __init__(self, arrays: dict[str, np.ndarray], metadata: dict[str, Any] | None = None):
        missing = [k for k in _LAYERS if k not in arrays]
        if missing:
            raise ValueError(f"policy weights: missing arrays {missing}")
        self.w0, self.b0, self.w1, self.b1, self.w2, self.b2 = (
            np.ascontiguousarray(arrays[k], dtype=np.float32) for k in _LAYERS)
        for i, (w, b) in enumerate(((self.w0, self.b0), (self.w1, self.b1), (self.w2, self.b2))):
            if w.ndim != 2 or b.shape != (w.shape[1],):
                raise ValueError(f"policy weights: w{i} {w.shape} / b{i} {b.shape} do not match")
        if self.w1.shape[0] != self.w0.shape[1] or self.w2.shape[0] != self.w1.shape[1]:
            raise ValueError("policy weights: layer sizes do not chain")
        self.log_std = np.asarray(arrays.get("log_std", np.zeros(self.w2.shape[1])), np.float32)
        self.obs_dim, self.act_dim = self.w0.shape[0], self.w2.shape[1]
        self.metadata = dict(metadata or {})
        self.obs_stack = int(self.metadata.get("obs_stack", 1))
        """Scans per observation, newest first (1: the paper's single scan)."""
        if self.obs_stack < 1 or self.obs_dim % self.obs_stack:
            raise ValueError(f"policy metadata: obs_stack {self.obs_stack} does not divide the input size {self.obs_dim}")
        self.obs_stride = int(self.metadata.get("obs_stride", 1))
        """Scan periods between the stacked scans (1: consecutive)."""
        if self.obs_stride < 1:
            raise ValueError(f"policy metadata: obs_stride {self.obs_stride} must be >= 1")
        from racecav.common.lidar import VIEWS

        view = self.metadata.get("lidar", "paper")
        if view not in VIEWS:
            raise ValueError(f"policy metadata: lidar {view!r} is not a view ({sorted(VIEWS)})")
        self.lidar = VIEWS[view]
        """The scan the policy was trained on (common/lidar.VIEWS; the paper's 90 deg unless
        its metadata says otherwise)."""
        bb = self.metadata.get("brake_below")
        self.brake_below = None if bb is None else float(bb)
        """a_T below this brakes (a policy trained with EnvConfig.brake_below); None: never."""
        if self.brake_below is not None and not -1.0 < self.brake_below <= 0.0:
            raise ValueError(f"policy metadata: brake_below {bb} is not in (-1, 0]")
        self.normalize = "obs_mean" in arrays
        if self.normalize:
            mean = np.asarray(arrays["obs_mean"], np.float64)
            var = np.asarray(arrays["obs_var"], np.float64)
            if mean.shape != (self.obs_dim,) or var.shape != (self.obs_dim,):
                raise ValueError(f"policy weights: obs_mean {mean.shape} / obs_var {var.shape} "
                                 f"must be ({self.obs_dim},)")
            self.obs_mean = mean.astype(np.float32)
            self.obs_eps = float(arrays.get("obs_eps", 1e-8))
            # Multiply by 1/std rather than divide: same result within float32 rounding.
            self.obs_inv_std = (1.0 / np.sqrt(var + self.obs_eps)).astype(np.float32)
            self.obs_var = var.astype(np.float32)
            self.obs_clip = float(arrays.get("obs_clip", 10.0))

    def normalize_obs(self, obs: np.ndarray) -> np.ndarray:
        """The observation as the network sees it (float32; identity without normalisation)."""
        x = np.asarray(obs, dtype=np.float32)
        if self.normalize:
            x = np.clip((x - self.obs_mean) * self.obs_inv_std, -self.obs_clip, self.obs_clip)
        return x

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic action(s).

        :param obs: one observation (170,) or a batch (B, 170): sanitised lidar ranges.
        :returns: float32 (2,) or (B, 2) in [-1, 1]: [a_T, a_delta].
        """
        x = self.normalize_obs(obs)
        if x.shape[-1] != self.obs_dim:
            raise ValueError(f"observation: expected last dimension {self.obs_dim}, got {x.shape}")
        h = np.tanh(x @ self.w0 + self.b0)
        h = np.tanh(h @ self.w1 + self.b1)
        a = h @ self.w2 + self.b2
        return np.clip(a, -1.0, 1.0, out=a)

    act = __call__

    @property
    def n_params(self) -> int:
        """Weights and biases of the actor."""
        return sum(int(getattr(self, k).size) for k in _LAYERS)

    def arrays(self) -> dict[str, np.ndarray]:
        """The npz contents (as saved)."""
        out = {k: getattr(self, k) for k in _LAYERS}
        out["log_std"] = self.log_std
        if self.normalize:
            out.update(obs_mean=self.obs_mean, obs_var=self.obs_var,
                       obs_clip=np.float32(self.obs_clip), obs_eps=np.float32(self.obs_eps))
        return out


def resolve_policy_path(name_or_path: str | Path) -> Path:
    """The ``.npz`` of a shipped name ("racing", "default", "reversed") or of a path (with or
    without the ``.npz``/``.json`` suffix)."""
    s = str(name_or_path)
    if s in SHIPPED:
        return MODELS_DIR / f"{s}.npz"
    p = Path(s)
    if p.suffix in (".json", ".zip"):
        p = p.with_suffix(".npz")
    elif p.suffix != ".npz":
        p = p.with_name(p.name + ".npz")
    return p


def load_policy(name_or_path: str | Path) -> NumpyPolicy:
    """Load a shipped policy by name or a policy file by path.

    :param name_or_path: "racing" | "default" | "reversed" | path to ``X.npz`` (``X.json`` is read
        if present).
    :raises FileNotFoundError: naming the file that is missing.
    """
    path = resolve_policy_path(name_or_path)
    if not path.is_file():
        raise FileNotFoundError(f"policy {name_or_path!r}: no weights file {path}")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta_path = path.with_suffix(".json")
    metadata = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    return NumpyPolicy(arrays, metadata)


def policy_arrays_from_sb3(sb3_model) -> dict[str, np.ndarray]:
    """The actor's weights of an SB3 PPO MlpPolicy (net_arch [64, 64], tanh) as npz arrays."""
    sd = {k: v.detach().cpu().numpy() for k, v in sb3_model.policy.state_dict().items()}
    lin = sorted({int(k.split(".")[2]) for k in sd if k.startswith("mlp_extractor.policy_net.")})
    if len(lin) != 2:
        raise ValueError(f"export: expected 2 hidden layers in the actor, found {len(lin)}")
    act_fn = type(sb3_model.policy.mlp_extractor.policy_net[1]).__name__
    if act_fn != "Tanh":
        raise ValueError(f"export: the numpy path implements tanh, the model uses {act_fn}")
    out = {}
    for i, j in enumerate(lin):
        out[f"w{i}"] = sd[f"mlp_extractor.policy_net.{j}.weight"].T.astype(np.float32)
        out[f"b{i}"] = sd[f"mlp_extractor.policy_net.{j}.bias"].astype(np.float32)
    out["w2"] = sd["action_net.weight"].T.astype(np.float32)
    out["b2"] = sd["action_net.bias"].astype(np.float32)
    out["log_std"] = sd["log_std"].astype(np.float32)
    return out


def export_policy(sb3_model, path: str | Path, metadata: dict[str, Any] | None = None,
                  obs_rms=None, clip_obs: float = 10.0, epsilon: float = 1e-8) -> Path:
    """Write ``path`` (.npz) and its ``.json`` metadata from an SB3 PPO model.

    :param sb3_model: a trained ``stable_baselines3.PPO`` with MlpPolicy [64, 64] tanh.
    :param path: target ``.npz`` (the suffix is forced).
    :param metadata: JSON-serialisable dict stored as ``.json``.
    :param obs_rms: VecNormalize's ``obs_rms`` (RunningMeanStd) if observations were normalised.
    :param clip_obs: VecNormalize's ``clip_obs``.
    :param epsilon: VecNormalize's ``epsilon``.
    :returns: the ``.npz`` path.
    """
    path = Path(path).with_suffix(".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = policy_arrays_from_sb3(sb3_model)
    meta = dict(metadata or {})
    if obs_rms is not None:  # the actor's inputs only (a privileged critic reads more: training/privileged.py)
        n_in = arrays["w0"].shape[0]
        arrays.update(obs_mean=np.asarray(obs_rms.mean, np.float64)[:n_in],
                      obs_var=np.asarray(obs_rms.var, np.float64)[:n_in],
                      obs_clip=np.float64(clip_obs), obs_eps=np.float64(epsilon))
    meta["normalization"] = ({"kind": "VecNormalize obs", "clip_obs": clip_obs, "epsilon": epsilon}
                             if obs_rms is not None else None)
    np.savez(path, **arrays)
    path.with_suffix(".json").write_text(json.dumps(meta, indent=2, sort_keys=True, default=str) + "\n")
    return path


def push_scans(hist: np.ndarray, obs: np.ndarray) -> None:
    """A batch's scan history (B, L, R), newest first: shifted by one, ``obs`` (B, R) in front."""
    hist[:, 1:] = hist[:, :-1]
    hist[:, 0] = obs


def stacked_scans(hist: np.ndarray, n: int, stride: int) -> np.ndarray:
    """(B, n * R) from a batch's history (B, L, R): each car's ``n`` scans ``stride`` apart, newest
    first, as :class:`ScanStack` gives one car's (a copy)."""
    return hist[:, ::stride][:, :n].reshape(hist.shape[0], -1).copy()


class ScanStack:
    """``n`` observations of one car, ``stride`` scans apart, newest first, as the training env
    stacks them: after a reset (or a gap: a lost scan, a new episode) the history is filled with
    the current one.

    :param n: scans per observation (a policy's ``obs_stack``).
    :param stride: scan periods between them (a policy's ``obs_stride``; 1: consecutive).
    """

    def __init__(self, n: int, stride: int = 1):
        self.n, self.stride = int(n), int(stride)
        self.buf: np.ndarray | None = None
        """The newest (n - 1) * stride + 1 observations, newest first."""

    def reset(self) -> None:
        self.buf = None

    def current(self) -> np.ndarray:
        """The stack after the last push (n * R,)."""
        return self.buf[::self.stride].reshape(-1) if self.stride > 1 else self.buf.reshape(-1)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Push one observation (R,) and return the stack (n * R,): for stride 1 a view of the
        stack's buffer, valid until the next push (copy it to keep it)."""
        obs = np.asarray(obs, dtype=np.float32)
        if self.n == 1:
            return obs
        if self.buf is None or self.buf.shape[1] != obs.shape[0]:
            self.buf = np.repeat(obs[None], (self.n - 1) * self.stride + 1, axis=0)
        else:  # in place (the service's hot path: no allocation); numpy handles the overlap
            self.buf[1:] = self.buf[:-1]
            self.buf[0] = obs
        return self.current()
