"""The shipped policy format: numpy inference equals SB3's deterministic action within 1e-5 on
recorded observations (tests/data/policy_obs.npz, from `record_observations` in
training/select.py), metadata, loading errors, and no torch/SB3 import on the numpy path."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from racecav.common.policy import (MODELS_DIR, SHIPPED, NumpyPolicy, export_policy, load_policy,
                                   policy_arrays_from_sb3)
from tests.recorded import recorded_obs

ROOT = Path(__file__).resolve().parents[1]
OBS = np.load(ROOT / "tests" / "data" / "policy_obs.npz")["obs"]
PRESENT = [n for n in SHIPPED if (MODELS_DIR / f"{n}.npz").is_file()]


def _sb3_actions(zip_path: Path, obs: np.ndarray) -> np.ndarray:
    """The reference path: SB3 PPO + its VecNormalize statistics, predict(deterministic=True)."""
    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(1)
    model = PPO.load(zip_path, device="cpu")
    vn = zip_path.with_suffix(".vecnorm.pkl")
    x = obs
    if vn.is_file():
        with vn.open("rb") as f:
            norm = pickle.load(f)
        norm.training = False
        x = norm.normalize_obs(obs)
    act, _ = model.predict(x, deterministic=True)
    return act


def test_racing_policy_is_shipped():
    assert "racing" in PRESENT


def stacked(obs: np.ndarray, k: int) -> np.ndarray:
    """Recorded observations as a stacked policy sees them: each with the k-1 before it."""
    return np.concatenate([np.roll(obs, i, axis=0) for i in range(k)], axis=1) if k > 1 else obs


@pytest.mark.parametrize("name", PRESENT)
def test_numpy_equals_sb3_on_recorded_observations(name):
    pol = load_policy(name)
    OBS = stacked(recorded_obs(pol.lidar), pol.obs_stack)
    ref = _sb3_actions(MODELS_DIR / f"{name}.zip", OBS)
    got = pol(OBS)
    assert got.dtype == np.float32 and got.shape == (len(OBS), 2)
    np.testing.assert_allclose(got, ref, atol=1e-5, rtol=0)
    # one observation at a time gives the same as the batch (float32: BLAS sums a batch and a
    # single vector in different orders, a few 1e-6 apart)
    for i in range(0, len(OBS), 17):
        np.testing.assert_allclose(pol(OBS[i]), got[i], atol=1e-5, rtol=0)
    # the recorded observations are not degenerate: the policy's actions differ between them
    assert np.ptp(got[:, 1]) > 0.05


@pytest.mark.parametrize("name", PRESENT)
def test_metadata(name):
    meta = json.loads((MODELS_DIR / f"{name}.json").read_text())
    for key in ("training_steps", "seed", "settings", "git_commit_training", "normalization"):
        assert key in meta, key
    assert meta["training_steps"] > 0
    pol = load_policy(name)
    assert pol.n_params == pol.lidar.n_rays * pol.obs_stack * 64 + 64 + 64 * 64 + 64 + 64 * 2 + 2
    assert pol.obs_stack == meta.get("obs_stack", 1)
    assert pol.normalize == (meta["normalization"] is not None)
    assert pol.metadata["training_steps"] == meta["training_steps"]


def test_export_roundtrip_with_normalisation(tmp_path):
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from racecav.training.vec_env import FastVecEnv

    torch.set_num_threads(1)
    venv = VecNormalize(FastVecEnv(n_envs=2, n_obstacles=0, seed=1))
    model = PPO("MlpPolicy", venv, n_steps=32, batch_size=64, n_epochs=1, seed=1, device="cpu",
                policy_kwargs=dict(net_arch=[64, 64], activation_fn=torch.nn.Tanh))
    model.learn(64)
    path = export_policy(model, tmp_path / "p", {"k": 1}, obs_rms=venv.obs_rms,
                         clip_obs=venv.clip_obs, epsilon=venv.epsilon)
    pol = load_policy(path)
    venv.training = False
    ref, _ = model.predict(venv.normalize_obs(OBS), deterministic=True)
    np.testing.assert_allclose(pol(OBS), ref, atol=1e-5, rtol=0)
    assert pol.metadata["k"] == 1 and pol.metadata["normalization"]["kind"].startswith("VecNormalize")
    # by path without suffix and with .json resolve to the same weights
    np.testing.assert_array_equal(load_policy(tmp_path / "p")(OBS[:3]), load_policy(tmp_path / "p.json")(OBS[:3]))
    # a re-export writes the same bytes (np.savez: fixed zip timestamps): the stored evaluation
    # cells keyed by its sha256 (evaluation/results.py) survive re-shipping a checkpoint
    first = path.read_bytes()
    time.sleep(2.1)  # zip timestamps have a 2 s resolution
    export_policy(model, tmp_path / "p", {"k": 1}, obs_rms=venv.obs_rms, clip_obs=venv.clip_obs,
                  epsilon=venv.epsilon)
    assert path.read_bytes() == first
    norm = {"obs_mean", "obs_var", "obs_clip", "obs_eps"}
    assert set(np.load(path).files) == set(policy_arrays_from_sb3(model)) | norm


def test_actions_are_clipped():
    rng = np.random.default_rng(0)
    arrays = {"w0": rng.normal(size=(170, 64)), "b0": np.zeros(64), "w1": rng.normal(size=(64, 64)),
              "b1": np.zeros(64), "w2": 50 * rng.normal(size=(64, 2)), "b2": np.zeros(2)}
    a = NumpyPolicy(arrays)(OBS)
    assert a.min() == -1.0 and a.max() == 1.0


def test_bad_files_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope"):
        load_policy(tmp_path / "nope")
    np.savez(tmp_path / "bad.npz", w0=np.zeros((170, 64)))
    with pytest.raises(ValueError, match="missing arrays"):
        load_policy(tmp_path / "bad.npz")
    arrays = {"w0": np.zeros((170, 64)), "b0": np.zeros(64), "w1": np.zeros((32, 64)),
              "b1": np.zeros(64), "w2": np.zeros((64, 2)), "b2": np.zeros(2)}
    with pytest.raises(ValueError, match="chain"):
        NumpyPolicy(arrays)
    arrays["w1"] = np.zeros((64, 64))
    with pytest.raises(ValueError, match="observation"):
        NumpyPolicy(arrays)(np.zeros(169))


def test_numpy_path_imports_no_torch():
    code = ("import sys; from racecav.common.policy import load_policy; "
            "from racecav.services.policy.fused import FusedPolicy; "
            "from racecav.common.lidar import LidarSpec; "
            "p = load_policy('racing'); p(__import__('numpy').full(170, 5.0)); "
            "FusedPolicy(p, LidarSpec())(__import__('numpy').full(170, 5.0)); "
            "print(sorted(m for m in ('torch', 'stable_baselines3') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
