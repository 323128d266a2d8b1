"""The ONNX export: onnxruntime equals the numpy reference within 1e-5 on recorded scans (and
on every kind of value sanitize handles), the sidecar says what the model expects, and
``racecav policy --backend onnxruntime|numpy`` drives on the bus like the fused default."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from racecav.common import keys, procs
from racecav.common.codec import encode
from racecav.common.lidar import LidarSpec, sanitize
from racecav.common.policy import MODELS_DIR, SHIPPED, load_policy
from tests.recorded import recorded_obs
from tests.test_controllers_policy import Commands, _test_scan, random_policy_file

pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")

ROOT = Path(__file__).resolve().parents[1]
SPEC = LidarSpec()
PRESENT = [n for n in SHIPPED if (MODELS_DIR / f"{n}.npz").is_file()]


def recorded_scans(view: LidarSpec | None = None) -> np.ndarray:
    """The recorded observations (tests/data) of a view as Scan ranges (nothing within range ->
    +inf), plus values the sensor may send: no return, beyond range, below range_min."""
    obs = recorded_obs(view).astype(np.float32)
    raw = np.where(obs >= SPEC.range_max, np.inf, obs).astype(np.float32)
    rng = np.random.default_rng(0)
    extra = raw[rng.integers(0, len(raw), 60)].copy()
    for value, p in ((np.inf, 0.1), (np.nan, 0.05), (-np.inf, 0.02), (0.0, 0.02), (30.0, 0.05)):
        extra[rng.random(extra.shape) < p] = value
    return np.concatenate([raw, extra])


@pytest.mark.parametrize("name", PRESENT)
def test_exported_model_equals_numpy_on_recorded_scans(tmp_path, name):
    out = tmp_path / name
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "train", "export", "--onnx", name, "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    onnx.checker.check_model(onnx.load(out / "model.onnx"))
    from racecav.services.policy.onnx_export import OnnxPolicy

    ort = OnnxPolicy(out / "model.onnx")
    pol = load_policy(name)
    scans = recorded_scans(pol.lidar)
    if pol.obs_stack > 1:  # each scan with the ones before it, newest first
        scans = np.concatenate([np.roll(scans, i, axis=0) for i in range(pol.obs_stack)], axis=1)
    ref = pol(sanitize(scans, SPEC))
    got = ort.batch(scans)
    assert got.shape == ref.shape and np.abs(got - ref).max() < 1e-5
    assert np.abs(np.array([ort(s) for s in scans[:20]]) - ref[:20]).max() < 1e-5  # single-scan path
    assert len(np.unique(got.round(3), axis=0)) > 20  # not a constant output
    meta = json.loads((out / "model.json").read_text())
    v = pol.lidar
    assert meta["input"]["rays"]["n"] == v.n_rays and meta["input"]["rays"]["angle_min"] == pytest.approx(v.angle_min)
    assert meta["input"]["stack"] == pol.obs_stack and meta["input"]["shape"][1] == v.n_rays * pol.obs_stack
    assert meta["output"]["actions"] == ["a_throttle", "a_steer"] and meta["output"]["clip"] == [-1.0, 1.0]
    assert meta["normalization"]["inside_model"] == pol.normalize and meta["network"]["n_params"] == pol.n_params


def test_unnormalised_policy_and_bad_name(tmp_path):
    from racecav.services.policy.onnx_export import OnnxPolicy, build_onnx

    pol = load_policy(random_policy_file(tmp_path / "pol.npz", seed=2, normalize=False))
    ort = OnnxPolicy(build_onnx(pol, SPEC))
    scans = recorded_scans()
    assert np.abs(ort.batch(scans) - pol(sanitize(scans, SPEC))).max() < 1e-5
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "train", "export", "--onnx", str(tmp_path / "nope")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "no weights file" in r.stdout


@pytest.mark.parametrize("backend", ["onnxruntime", "numpy"])
def test_policy_service_backends_match_the_reference(spawn, session, tmp_path, backend):
    path = random_policy_file(tmp_path / "pol.npz")
    ctl = spawn("policy", "--model", str(path), "--backend", backend)
    procs.wait_alive(session, "car0", "policy", proc=ctl)
    cmds = Commands(session)
    pub = session.declare_publisher(keys.topic("car0", keys.SCAN))
    pol = load_policy(path)
    rng = np.random.default_rng(3)
    scans = []
    for seq in range(5):
        scans.append(_test_scan(seq, rng))
        pub.put(encode(scans[-1]))
        cmds.wait(seq + 1)
    for scan, cmd in zip(scans, cmds.wait(5)):
        a = pol(sanitize(scan.ranges))
        assert cmd.scan_seq == scan.seq
        assert cmd.a_throttle == pytest.approx(float(a[0]), abs=1e-5)
        assert cmd.a_steer == pytest.approx(float(a[1]), abs=1e-5)
    from racecav.common.client import get_status

    assert get_status(session, "car0", "policy").info["backend"] == backend
    pub.undeclare()
    cmds.sub.undeclare()
