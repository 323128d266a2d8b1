"""Sim-to-real perturbations (common/perturb.py): each acts as specified, in both backends and
through the lockstep sim service, and a perturbed run repeats."""

import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from racecav.common import keys, perturb as P, procs
from racecav.common.codec import decode
from racecav.common.config import EnvConfig, PerturbConfig
from racecav.common.lidar import LidarSpec, ray_angles
from racecav.common.messages import Scan, VehicleState

SPEC = LidarSpec()


def test_range_noise_statistics():
    """Absolute and range-proportional noise add in quadrature; no return stays no return."""
    p = PerturbConfig(range_noise_m=0.02, range_noise_rel=0.01)
    r = np.full((400, SPEC.n_rays), 3.0, np.float32)
    r[:, :10] = np.inf
    out = P.perturb_scan(r, SPEC, p, P.trial_rng(1))
    d = out[:, 10:].astype(np.float64) - 3.0
    assert abs(d.mean()) < 0.002
    assert d.std() == pytest.approx(math.hypot(0.02, 0.03), rel=0.03)
    assert np.isinf(out[:, :10]).all()


def test_dropped_returns_share_and_the_sensor_services_hole_filling():
    """Dropped rays follow the share (isolated returns, 8 deg apart: too far apart to fill); along a
    wall they are filled by interpolation (the sensor service's fill_holes), as on the car."""
    p = PerturbConfig(dropout=0.1)
    sparse = np.full((400, SPEC.n_rays), np.inf, np.float32)
    sparse[:, ::15] = 3.0
    out = P.perturb_scan(sparse, SPEC, p, P.trial_rng(2))
    assert np.isinf(out[:, ::15]).mean() == pytest.approx(0.1, abs=0.015)
    assert np.isinf(out[:, 1::15]).all()  # a true no return between them stays one
    r = np.tile(np.linspace(2.0, 4.0, SPEC.n_rays, dtype=np.float32), (2000, 1))
    out = P.perturb_scan(r, SPEC, p, P.trial_rng(2))
    assert np.isfinite(out).mean() > 0.999  # holes wider than 6 deg (11 rays) are that rare
    ok = np.isfinite(out)
    err = np.where(ok, np.abs(out - r), 0.0)
    assert err[:, 12:-12].max() < 1e-4  # linear: exact (holes reach at most 11 rays)
    assert err.max() < 0.012  # the edges: from the virtual sample beyond them (half a ray's slope)
    # a hole wider than SensorConfig.max_gap_deg stays open, as on the car
    from racecav.common.lidar import fill_holes

    th = ray_angles(SPEC).astype(np.float64)
    ok = np.ones(SPEC.n_rays, bool)
    ok[50:70] = False  # 20 rays = 10.7 deg
    ok[100] = False
    filled = fill_holes(th, np.full(SPEC.n_rays, 2.0), ok, 6.0)
    assert np.isinf(filled[50:70]).all() and filled[100] == 2.0


def test_unknown_keys_and_presets_are_named(tmp_path):
    bad = tmp_path / "p.toml"
    bad.write_text("[worn]\nsteer_ofset_rad = 0.01\n")
    with pytest.raises(ValueError, match=r"\[worn\]: unknown key 'steer_ofset_rad'"):
        P.load_presets(bad)
    with pytest.raises(ValueError, match="unknown key 'latency'"):
        P.parse_text("s2-nominal,latency=0.05")
    assert set(P.load_presets()) >= {"s2-nominal", "s2-pessimistic", "worn-car", "slippery-floor", "late-computer"}
    assert PerturbConfig.model_validate("s2-nominal,latency_s=0.05").text() == \
        "dropout=0.02,latency_s=0.05,range_noise_m=0.015"
    from racecav.evaluation import suite as S

    S.generate(S.load_families("open"), tmp_path / "open", n_test=1, n_train=1, seed=1, progress=False)
    for argv in (["sim", "--perturb", "late-computer,bogus=1"],
                 ["eval", "--scenario", "head-to-head", "--controller", "scripted", "--perturb", "s2-nominl"],
                 ["eval", "--suite", str(tmp_path / "open"), "--controller", "scripted", "--perturb", "s2-nominl"]):
        r = subprocess.run([sys.executable, "-m", "racecav.cli", *argv], capture_output=True, text=True, timeout=60)
        out = (r.stdout + r.stderr).strip().splitlines()
        assert r.returncode == 2 and len(out) == 1 and ("'bogus'" in out[0] or "'s2-nominl'" in out[0]), out


@pytest.mark.parametrize("friction", [0.523])
def test_lower_friction_lengthens_the_stop_in_both_backends(tmp_path, friction):
    """Braking from 2 m/s on the open floor: the stopping distance grows on a slippery floor, in
    PyBullet (its Coulomb friction) and in the fast world (friction x the fitted deceleration),
    and the two agree within the braking parity tolerance (docs/training-env.md)."""
    from racecav.sim.bullet_world import BulletWorld
    from racecav.sim.fast_world import FastWorld
    from racecav.training.fit_bicycle import open_floor_scenario

    sc = open_floor_scenario(tmp_path)
    dist = {}
    for mu in (1.0, friction):
        p = PerturbConfig(friction=mu)
        with BulletWorld(sc, perturb=p) as bw:
            bw.reset(seed=0, options={"agent_speed": 2.0})
            x0 = bw.agent_state()[0, :2].copy()
            for _ in range(20):
                bw.step(np.array([[-1.0, 0.0]]), brake=np.array([True]))
            dist[("bullet", mu)] = float(np.hypot(*(bw.agent_state()[0, :2] - x0)))
        fw = FastWorld(n_envs=1, scenarios=[sc], perturb=p)
        fw.reset(seed=0)
        fw.set_state(0, 0, x=0.0, y=0.0, yaw=0.0, v=2.0)
        for _ in range(20):
            fw.step(np.array([[-1.0, 0.0]]), brake=np.array([True]))
        dist[("fast", mu)] = float(np.hypot(*fw.agent_state()[0, :2]))
    for backend in ("bullet", "fast"):
        assert dist[(backend, friction)] > 1.5 * dist[(backend, 1.0)], dist
    assert abs(dist[("bullet", friction)] - dist[("fast", friction)]) < 0.10, dist  # the 10 cm parity


def test_fast_world_delays_the_agents_actions():
    """latency + actuator delay: the new action reaches the actuators that long into the period
    (at the next substep); the steering offset turns a straight command."""
    from racecav.common.scenario import load_scenario
    from racecav.sim.fast_world import FastWorld

    sc = load_scenario("conflict-right-to-left")
    fws = {d: FastWorld(n_envs=1, scenarios=[sc], perturb=PerturbConfig(latency_s=d)) for d in (0.0, 0.05, 0.15)}
    speeds = {}
    for d, fw in fws.items():
        fw.reset(seed=0)
        fw.set_state(0, 0, v=0.0)
        vs = []
        for k in range(4):
            fw.step(np.array([[1.0, 0.0]]))
            vs.append(fw.agent_state()[0, 3])
        speeds[d] = vs
    assert speeds[0.0][0] > speeds[0.05][0] > 0.0 and speeds[0.15][0] == 0.0 and speeds[0.15][1] > 0.0
    fw = FastWorld(n_envs=1, scenarios=[sc], perturb=PerturbConfig(steer_offset_rad=0.05))
    fw.reset(seed=0)
    for _ in range(10):
        fw.step(np.array([[1.0, 0.0]]))
    assert fw.delta[0, 0] == pytest.approx(0.05, abs=1e-3)


class _Listen:
    def __init__(self, session, key, cls):
        self.items, self.cls, self._lock = [], cls, threading.Lock()
        self.sub = session.declare_subscriber(keys.topic("car0", key), self._on)

    def _on(self, sample):
        with self._lock:
            self.items.append(decode(sample.payload.to_bytes(), self.cls))

    def by_seq(self):
        with self._lock:
            return sorted({m.seq: m for m in self.items}.values(), key=lambda m: m.seq)


def _run(spawn, session, env: dict, report_ms: str | None) -> tuple[list, list]:
    """A lockstep sim under ``env`` driven by a scripted program: (states, scan ranges) by seq."""
    sim = spawn("sim", "--scenario", "right-to-left", "--mode", "lockstep", "--seed", "3", env=env)
    procs.wait_alive(session, "car0", "sim", proc=sim)
    states, scans = _Listen(session, keys.STATE, VehicleState), _Listen(session, keys.SCAN, Scan)
    ctl = spawn("scripted", "--program", "0.3,0.2,8;0.5,-0.3,8;0.2,0.0,100",
                *(["--compute-ms", report_ms] if report_ms else []))
    deadline = time.monotonic() + 60
    while len(states.by_seq()) < 30 and time.monotonic() < deadline:
        time.sleep(0.05)
    procs.stop(ctl)
    procs.stop(sim)
    st = [(s.seq, s.x, s.y, s.yaw, s.vx) for s in states.by_seq()][:30]
    sc = [s.ranges.copy() for s in scans.by_seq()][:30]
    states.sub.undeclare()
    scans.sub.undeclare()
    return st, sc


def test_lockstep_sim_charges_the_latency_and_repeats(spawn, session):
    """The sim applies a command latency_s + actuator_delay_s after its compute time: 13 ms
    reported + 50 ms perturbed drives exactly as a fixed charge of 63 ms; a perturbed run (noisy
    scans, dropouts, jitter) repeats to the bit."""
    pert = '{"latency_s": 0.04, "actuator_delay_s": 0.01}'
    late, _ = _run(spawn, session, {"RACECAV_SIM__PERTURB": pert}, "13")
    charged, _ = _run(spawn, session, {"RACECAV_SIM__LOCKSTEP_COMPUTE_MS": "63"}, None)
    plain, _ = _run(spawn, session, {}, "13")
    assert len(late) == len(charged) == 30
    assert np.allclose(np.array(late), np.array(charged), atol=1e-6)
    assert np.abs(np.array(late) - np.array(plain)).max() > 0.01  # the latency moved the car
    env = {"RACECAV_SIM__PERTURB": "s2-pessimistic,latency_s=0.03"}
    a, sa = _run(spawn, session, env, "13")
    b, sb = _run(spawn, session, env, "13")
    assert a == b and len(sa) == len(sb) == 30
    assert all(np.array_equal(x, y) for x, y in zip(sa, sb))
