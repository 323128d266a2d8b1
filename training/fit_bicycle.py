"""Fit the fast backend's single-track model to rollouts of the PyBullet car.

``python -m racecav.training.fit_bicycle [--car slash] [--sequences 64] [--write]``
``python -m racecav.training.fit_bicycle --report`` (parity section of docs/training-env.md)

Both backends start from the same state on an open floor (no walls within lidar range) and play
the same action sequences (see :func:`fit_dataset`: random piecewise-constant actions held
0.2-1.0 s and randomised transient-rich manoeuvres, i.e. slaloms, full-lock reversals, coasting
turns and bang-bang pulses; both speed scales: obstacle car 1.0 and racetrack agent
``agent_speed_scale``; half of them from a random heading). Nelder-Mead adjusts the BicycleParams
fields of the fast single-track model (see FIT) to minimise the mean squared position error over
every step; ``--write`` stores the result in the car file's ``[bicycle]`` section (with
``fitted = true``). The same helpers serve the parity tests.

What the model reproduces of the PyBullet car (measured, see docs/training-env.md):

- its steering joint (position control, PyBullet's default gain 0.1) moves 0.1 of the remaining
  error per physics step, exactly a first-order lag of ``physics_dt / 0.1`` (0.25 s): not fitted;
- its tyres' grip depends on the heading relative to the world axes (measured: a steady turn's
  curvature breathes by +-15 % with a period of 90 deg of heading, and the same manoeuvre from
  another heading turns differently; presumably the friction directions of PyBullet's contacts
  with the ground plane are tied to the world axes): ``heading_c4``/``heading_s4``. A model
  without it misses by 10-20 cm whenever a reversal falls at another phase;
- its locked 4WD scrub: effective wheelbase ~0.39 m, speed loss in turns, cornering stiffnesses
  that fall with speed (``c_speed_inv``).
"""

from __future__ import annotations

import argparse
import math
import re
import tempfile
from pathlib import Path

import numpy as np

from racecav.common.vehicle import CARS_DIR, BicycleParams, CarParams, load_car

OPEN_FLOOR = """name = "open-floor"
kind = "roads"
description = "open floor for fitting and parity tests (walls 40 m away, beyond lidar range)"
lane_width = 80.0
[[roads]]
cx = 0.0
cy = 0.0
yaw_deg = 0.0
length = 80.0
width = 80.0
"""


def open_floor_scenario(tmpdir: str | Path):
    """A Scenario on an open floor (written to ``tmpdir``), ego at the origin facing +x."""
    from racecav.common.scenario import EgoStart, Scenario, Success

    path = Path(tmpdir) / "open-floor.toml"
    path.write_text(OPEN_FLOOR)
    return Scenario(name="open-floor", world=str(path), duration_s=1000.0,
                    ego=EgoStart(x=0.0, y=0.0, yaw_deg=0.0), success=Success(min_progress_m=0.0))


def random_actions(rng: np.random.Generator, n_seq: int, n_steps: int) -> np.ndarray:
    """(S, T, 2) piecewise-constant actions, each held 2-10 control steps: throttle in [-0.2, 1]
    (some coasting) but half of the time in [0.7, 1] (the reward 5 T^2 makes the policy drive
    flat out), steering in [-1.2, 1.2] (beyond the limits too: full lock is common)."""
    out = np.zeros((n_seq, n_steps, 2))
    for s in range(n_seq):
        t = 0
        while t < n_steps:
            hold = int(rng.integers(2, 11))
            thr = rng.uniform(0.7, 1.0) if rng.random() < 0.5 else rng.uniform(-0.2, 1.0)
            out[s, t:t + hold] = [thr, rng.uniform(-1.2, 1.2)]
            t += hold
    return out


def bullet_rollouts(scenario, car: CarParams, actions: np.ndarray, v0: np.ndarray,
                    scales: np.ndarray, yaw0: np.ndarray | None = None) -> np.ndarray:
    """(S, T+1, 4) x, y, yaw, v of the PyBullet agent from (0, 0, yaw0 (default 0), v0) under
    ``actions``."""
    from racecav.sim.bullet_world import BulletWorld

    S, T, _ = actions.shape
    yaw0 = np.zeros(S) if yaw0 is None else yaw0
    out = np.zeros((S, T + 1, 4))
    with BulletWorld(scenario, car=car, seed=0) as bw:
        for s in range(S):
            bw.reset(seed=0)
            bw.cars[0].speed_scale = float(scales[s])  # agent speed scale (racetrack agent: 1.5)
            bw.set_state(x=0.0, y=0.0, yaw=float(yaw0[s]), v=float(v0[s]))
            out[s, 0] = bw.agent_state()[0]
            for t in range(T):
                bw.step(actions[s, t][None])
                out[s, t + 1] = bw.agent_state()[0]
    return out


def fast_rollouts(world, car: CarParams, bicycle, actions: np.ndarray, v0: np.ndarray,
                  scales: np.ndarray, yaw0: np.ndarray | None = None) -> np.ndarray:
    """The same rollouts in the fast backend (all sequences as one batch)."""
    from racecav.sim.fast_world import FastWorld

    S, T, _ = actions.shape
    yaw0 = np.zeros(S) if yaw0 is None else yaw0
    fw = FastWorld(n_envs=S, world=world, car=car, n_obstacles=0)
    fw.set_bicycle(bicycle)
    fw.reset(seed=0)
    fw.speed_scale[:, 0] = scales
    for s in range(S):
        fw.set_state(s, 0, x=0.0, y=0.0, yaw=float(yaw0[s]), v=float(v0[s]),
                     w=float(v0[s]) / (car.wheel_radius * scales[s]), delta=0.0)
    out = np.zeros((S, T + 1, 4))
    out[:, 0] = fw.agent_state()
    for t in range(T):
        fw.step(actions[:, t])
        out[:, t + 1] = fw.agent_state()
    return out


DESIGNED = ("slalom", "hard-left-then-right", "coast-and-turn", "pulses")
"""Designed 3 s sequences of mixed throttle and steering (parity tests and report)."""


def designed_actions(kind: str, n_steps: int = 30, dt: float = 0.1) -> np.ndarray:
    """(T, 2) actions of a designed sequence (see DESIGNED)."""
    t = np.arange(n_steps) * dt
    if kind == "slalom":
        return np.stack([0.6 + 0.4 * np.sin(2.0 * t), 0.3 * np.sin(1.5 * t)], 1)
    if kind == "hard-left-then-right":
        return np.stack([np.ones(n_steps), np.where(t < 1.5, 1.0, -1.0)], 1)
    if kind == "coast-and-turn":
        return np.stack([np.where(t < 1.0, 1.0, np.where(t < 2.0, 0.0, 0.7)),
                         np.where(t < 1.0, 0.0, 0.25)], 1)
    if kind == "pulses":
        return np.stack([(np.sin(4.0 * t) > 0).astype(float), 0.5 * np.sign(np.sin(1.0 * t + 0.3))], 1)
    raise ValueError(f"unknown designed sequence {kind!r} (known: {DESIGNED})")


def transient_actions(rng: np.random.Generator, n_seq: int, n_steps: int, dt: float = 0.1) -> np.ndarray:
    """(S, T, 2) randomised variants of the DESIGNED families (other amplitudes, frequencies,
    phases and switch times; not the designed sequences themselves): sinusoidal slaloms with a
    modulated throttle, (near) full-lock reversals at high throttle, coasting/braking phases with
    turns, bang-bang throttle and steering pulses."""
    t = np.arange(n_steps) * dt
    out = np.zeros((n_seq, n_steps, 2))
    u = rng.uniform
    for i in range(n_seq):
        kind = i % 4
        if kind == 0:
            thr = np.clip(u(0.3, 0.8) + u(0, 0.5) * np.sin(u(1, 4) * t + u(0, 6)), -0.2, 1.0)
            out[i] = np.stack([thr, u(0.2, 1.2) * np.sin(u(0.8, 3) * t + u(0, 6))], 1)
        elif kind == 1:
            a = u(0.6, 1.2) * rng.choice([-1.0, 1.0])
            out[i] = np.stack([np.full(n_steps, u(0.6, 1.0)), np.where(t < u(0.5, 2.5), a, -a * u(0.6, 1.0))], 1)
        elif kind == 2:
            t1, t2 = np.sort(u(0.3, 2.7, 2))
            out[i] = np.stack([np.where(t < t1, 1.0, np.where(t < t2, u(-0.2, 0.3), u(0.5, 1.0))),
                               np.where(t < t1, u(-0.3, 0.3), u(-1.2, 1.2))], 1)
        else:
            out[i] = np.stack([(np.sin(u(2, 6) * t + u(0, 6)) > u(-0.5, 0.5)).astype(float),
                               u(0.3, 1.2) * np.sign(np.sin(u(0.7, 3) * t + u(0, 6)))], 1)
    return out


def fit_dataset(rng: np.random.Generator, n_seq: int, n_steps: int, car: CarParams):
    """Actions, v0, speed scales and start headings of a fit set: half random held actions, half
    :func:`transient_actions`; 30 % from rest; alternating speed scales; half of the sequences
    from a random heading (PyBullet's grip depends on it), the others from yaw 0."""
    h = n_seq // 2
    acts = np.concatenate([random_actions(rng, h, n_steps), transient_actions(rng, n_seq - h, n_steps)])
    v0 = np.where(rng.random(n_seq) < 0.3, 0.0, rng.uniform(0.3, 2.4, n_seq))
    scales = np.where(np.arange(n_seq) % 2 == 0, 1.0, car.agent_speed_scale)
    yaw0 = np.where(rng.random(n_seq) < 0.5, 0.0, rng.uniform(-math.pi, math.pi, n_seq))
    return acts, v0, scales, yaw0


def position_errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(S, T+1) distance between two sets of trajectories."""
    return np.hypot(a[..., 0] - b[..., 0], a[..., 1] - b[..., 1])


def nelder_mead(f, x0: np.ndarray, step: np.ndarray, iters: int = 300, tol: float = 1e-7):
    """Minimise f from x0 (plain Nelder-Mead; no scipy in the environment)."""
    n = len(x0)
    pts = [x0] + [x0 + np.eye(n)[i] * step[i] for i in range(n)]
    vals = [f(p) for p in pts]
    for _ in range(iters):
        order = np.argsort(vals)
        pts, vals = [pts[i] for i in order], [vals[i] for i in order]
        if abs(vals[-1] - vals[0]) < tol:
            break
        c = np.mean(pts[:-1], axis=0)
        xr = c + (c - pts[-1])
        fr = f(xr)
        if fr < vals[0]:
            xe = c + 2 * (c - pts[-1])
            fe = f(xe)
            pts[-1], vals[-1] = (xe, fe) if fe < fr else (xr, fr)
        elif fr < vals[-2]:
            pts[-1], vals[-1] = xr, fr
        else:
            xc = c + 0.5 * (pts[-1] - c)
            fc = f(xc)
            if fc < vals[-1]:
                pts[-1], vals[-1] = xc, fc
            else:
                pts = [pts[0]] + [pts[0] + 0.5 * (p - pts[0]) for p in pts[1:]]
                vals = [vals[0]] + [f(p) for p in pts[1:]]
    i = int(np.argmin(vals))
    return pts[i], vals[i]


# fitted fields, their lower/upper bounds and Nelder-Mead initial steps (mu is fixed: only the
# products mu * c_s enter the model; steer_tau is PyBullet's, see steer_tau_of)
FIT = {"lf": (0.02, 1.0, 0.03), "lr": (0.0, 1.0, 0.03), "iz": (0.001, 5.0, 0.1),
       "c_sf": (0.5, 500.0, 5.0), "c_sr": (0.5, 500.0, 2.0), "speed_tau": (0.0, 1.0, 0.05),
       "scrub": (0.0, 5.0, 0.2), "scrub_lat": (0.0, 0.2, 0.01), "c_speed_inv": (-0.4, 1.5, 0.1),
       "heading_c4": (-0.5, 0.5, 0.05), "heading_s4": (-0.5, 0.5, 0.05)}

BULLET_POSITION_GAIN = 0.1
"""PyBullet's default positionGain of POSITION_CONTROL: the steering joint closes this fraction of
its error per physics step (measured: the joint angle follows it to 1e-4 rad)."""


def steer_tau_of(car: CarParams) -> float:
    """The fast model's steering lag that reproduces PyBullet's steering joint exactly: the kernel
    closes ``physics_dt / steer_tau`` of the error per substep."""
    return car.physics_dt / BULLET_POSITION_GAIN


def _params(x: np.ndarray, base: BicycleParams) -> BicycleParams:
    upd = {k: float(min(max(v, FIT[k][0]), FIT[k][1])) for k, v in zip(FIT, x)}
    return base.model_copy(update=upd)


def _dataset(rng: np.random.Generator, n_seq: int, n_steps: int, car: CarParams):
    acts = random_actions(rng, n_seq, n_steps)
    v0 = np.where(rng.random(n_seq) < 0.3, 0.0, rng.uniform(0.3, 2.4, n_seq))
    scales = np.where(np.arange(n_seq) % 2 == 0, 1.0, car.agent_speed_scale)
    return acts, v0, scales


def fit(car: CarParams, n_seq: int = 256, n_steps: int = 30, seed: int = 0, iters: int = 600,
        restarts: int = 4, log=print) -> tuple[BicycleParams, dict]:
    """Collect PyBullet rollouts and fit; returns the fitted parameters and error statistics.

    Each start point is fitted on the training sequences (:func:`fit_dataset`); the result with
    the lowest error on held-out sequences (same distribution, other seed) wins, and its held-out
    errors are reported. The objective is the mean squared position error over every step: a
    worst-case-weighted one (plus the mean of the largest 10 % final errors) was measured and gave
    larger worst cases on the designed sequences (7.1 against 5.8 cm, on an earlier variant).
    """
    from racecav.common.world import load_world

    train = fit_dataset(np.random.default_rng(seed), n_seq, n_steps, car)
    held = fit_dataset(np.random.default_rng(seed + 1000), n_seq, n_steps, car)
    with tempfile.TemporaryDirectory() as tmp:
        sc = open_floor_scenario(tmp)
        world = load_world(sc.world)
        log(f"PyBullet: 2 x {n_seq} rollouts of {n_steps} steps ...")
        ref = bullet_rollouts(sc, car, *train)
        vref = bullet_rollouts(sc, car, *held)
        base = car.bicycle.model_copy(update={"steer_tau": steer_tau_of(car)})

        def errors(b, data, r):
            return position_errors(fast_rollouts(world, car, b, *data), r)

        def loss(x):
            return float(np.mean(errors(_params(x, base), train, ref) ** 2))

        x0 = np.array([getattr(base, k) for k in FIT])
        # Start points: the current parameters, and a guess from what PyBullet's car shows: a
        # steady-state effective wheelbase ~0.39 m with the no-slip point near the rear axle, a
        # stiff front, a +-15 % heading term. Nelder-Mead gets stuck easily in 11 dimensions.
        guess = base.model_copy(update={"lf": 0.32, "lr": 0.07, "iz": 1.0, "c_sf": 200.0, "c_sr": 30.0,
                                        "speed_tau": 0.0, "scrub": 0.0, "scrub_lat": 0.015,
                                        "c_speed_inv": 1.0, "heading_c4": 0.15, "heading_s4": -0.04})
        best, best_val = base, float(np.mean(errors(base, held, vref) ** 2))
        for start in (x0, np.array([getattr(guess, k) for k in FIT])):
            x = start
            for _ in range(restarts):  # restarting from the best point escapes a collapsed simplex
                x, val = nelder_mead(loss, x, np.array([v[2] for v in FIT.values()]), iters=iters)
            cand = _params(x, base)
            cval = float(np.mean(errors(cand, held, vref) ** 2))
            log(f"  start {np.round(start, 3).tolist()}: train rmse {math.sqrt(val):.4f} m, "
                f"held-out rmse {math.sqrt(cval):.4f} m")
            if cval < best_val:
                best, best_val = cand, cval
        fitted = best.model_copy(update={"fitted": True})
        err0 = errors(car.bicycle, train, ref)  # the car file's model before this fit
        err1 = errors(fitted, train, ref)
        errv = errors(fitted, held, vref)
    stats = {"rmse_before": float(np.sqrt(np.mean(err0 ** 2))), "rmse_after": float(np.sqrt(np.mean(err1 ** 2))),
             "final_err_median_before": float(np.median(err0[:, -1])),
             "final_err_median_after": float(np.median(err1[:, -1])),
             "final_err_p90_after": float(np.percentile(err1[:, -1], 90)),
             "final_err_max_after": float(err1[:, -1].max()),
             "heldout_rmse": float(np.sqrt(np.mean(errv ** 2))),
             "heldout_final_err_median": float(np.median(errv[:, -1])),
             "heldout_final_err_p90": float(np.percentile(errv[:, -1], 90)),
             "heldout_final_err_max": float(errv[:, -1].max()),
             "horizon_s": n_steps * car.control_period_s, "sequences": n_seq}
    return fitted, stats


def wall_range_errors(car: CarParams, n_poses: int = 24, seed: int = 0) -> np.ndarray:
    """|fast - PyBullet| wall ranges (m) of the agent at random racetrack poses (same pose in both)."""
    import math as m

    from racecav.common.config import EnvConfig
    from racecav.sim.fast_world import FastWorld
    from racecav.training.env import make_world

    bw = make_world(EnvConfig(backend="bullet", n_obstacles=0), seed=seed)
    fw = FastWorld(n_envs=1, n_obstacles=0, car=car, seed=seed)
    try:
        bw.reset(seed=seed)
        fw.reset(seed=seed)
        rng = np.random.default_rng(seed)
        out = []
        for _ in range(n_poses):
            x, y, yaw = fw.world.centerline_pose(rng.uniform(0, fw.world.length))
            off = rng.uniform(-0.6, 0.6)
            x, y, yaw = x - off * m.sin(yaw), y + off * m.cos(yaw), yaw + rng.uniform(-0.5, 0.5)
            bw.set_state(x=x, y=y, yaw=yaw)
            fw.set_state(0, 0, x=x, y=y, yaw=yaw, v=0.0, w=0.0, delta=0.0)
            rb, rf = bw.scan_ranges, fw.ranges[0, 0]
            both = np.isfinite(rb) & np.isfinite(rf)
            out.append(np.abs(rb[both] - rf[both]))
        return np.concatenate(out)
    finally:
        bw.close()


def gap_follower(obs: np.ndarray, angles: np.ndarray, throttle: float = 0.7) -> np.ndarray:
    """A scripted lidar controller (steer towards the widest far opening): closed-loop parity."""
    r = np.convolve(obs, np.ones(15) / 15, mode="same")
    return np.array([[throttle, np.clip(1.5 * angles[int(np.argmax(r))], -1.0, 1.0)]])


def closed_loop(car: CarParams, scale: float, steps: int = 300, s0: float = 3.0):
    """Both backends driven by :func:`gap_follower` on their own scans from the same start on
    the racetrack (no traffic). :return: (bullet (T, 4), fast (T, 4), first contact step of
    each (or None))."""
    from racecav.common.config import EnvConfig
    from racecav.common.lidar import ray_angles
    from racecav.sim.fast_world import FastWorld
    from racecav.training.env import make_world

    ang = ray_angles(car.lidar).astype(np.float64)
    bw = make_world(EnvConfig(backend="bullet", n_obstacles=0, agent_speed_scale=scale), seed=0)
    fw = FastWorld(1, n_obstacles=0, car=car, agent_speed_scale=scale, seed=0)
    try:
        bw.reset(seed=0)
        fw.reset(seed=0)
        x, y, yaw = fw.world.centerline_pose(s0)
        bw.set_state(x=x, y=y, yaw=yaw)
        fw.set_state(0, 0, x=x, y=y, yaw=yaw, v=0.0)
        ob, of = bw._observe()[None], fw.agent_obs()
        tb, tf, hit = [], [], [None, None]
        for k in range(steps):
            ob, _, cb, _ = bw.step(gap_follower(ob[0], ang))
            of, _, cf, _ = fw.step(gap_follower(of[0], ang))
            tb.append(bw.agent_state()[0])
            tf.append(fw.agent_state()[0])
            for i, c in enumerate((cb[0], cf[0])):
                if c and hit[i] is None:
                    hit[i] = k
            if hit[0] is not None and hit[1] is not None:
                break
        return np.array(tb), np.array(tf), hit
    finally:
        bw.close()


def parity_report(car: CarParams, log=print) -> str:
    """Markdown: the fast backend against PyBullet with the car file's fitted model."""
    from racecav.common.world import load_world

    combos = [(k, v0, s) for k in DESIGNED for v0 in (0.0, 1.2) for s in (1.0, car.agent_speed_scale)]
    acts = np.stack([designed_actions(k) for k, _, _ in combos])
    v0 = np.array([c[1] for c in combos])
    scales = np.array([c[2] for c in combos])
    with tempfile.TemporaryDirectory() as tmp:
        sc = open_floor_scenario(tmp)
        world = load_world(sc.world)
        log("PyBullet: designed and random rollouts ...")
        ref = bullet_rollouts(sc, car, acts, v0, scales)
        got = fast_rollouts(world, car, car.bicycle, acts, v0, scales)
        dflt = fast_rollouts(world, car, BicycleParams(), acts, v0, scales)
        rnd = _dataset(np.random.default_rng(777), 32, 30, car)
        rref = bullet_rollouts(sc, car, *rnd)
        rerr = position_errors(fast_rollouts(world, car, car.bicycle, *rnd), rref)[:, -1]
        mix = fit_dataset(np.random.default_rng(778), 64, 30, car)
        herr = position_errors(fast_rollouts(world, car, car.bicycle, *mix), bullet_rollouts(sc, car, *mix))[:, -1]
    err = position_errors(got, ref)[:, -1]
    derr = position_errors(dflt, ref)[:, -1]
    yerr = np.abs(np.angle(np.exp(1j * (got[:, -1, 2] - ref[:, -1, 2]))))
    travelled = np.hypot(*(ref[:, -1, :2] - ref[:, 0, :2]).T)
    rows = [f"| {k} | {v:.1f} | {s:.1f} | {d:.2f} | {e * 100:.1f} | {y:.3f} | {de * 100:.1f} |"
            for (k, v, s), d, e, y, de in zip(combos, travelled, err, yerr, derr)]
    log("closed loop: a lidar gap follower in both backends ...")
    cl_rows = []
    for scale in (1.0, car.agent_speed_scale):
        tb, tf, hit = closed_loop(car, scale)
        end = min(hit[0] if hit[0] is not None else len(tb), hit[1] if hit[1] is not None else len(tf))
        e = np.hypot(*(tb[:end, :2] - tf[:end, :2]).T)
        cl_rows.append(f"| {scale:.1f} | {hit[0]} | {hit[1]} | {e.max() * 100:.1f} | {end * car.control_period_s:.1f} |")
    log("lidar: wall ranges at random racetrack poses ...")
    wr = wall_range_errors(car)
    b = car.bicycle
    return "\n".join([
        "Same initial state, same actions, 3 s (30 control periods), open floor. Speed scale 1.0 is an",
        f"obstacle car, {car.agent_speed_scale:g} the racetrack agent. Fitted model: lf {b.lf:.3f}, lr {b.lr:.3f}, "
        f"iz {b.iz:.3f}, c_sf {b.c_sf:.2f}, c_sr {b.c_sr:.2f}, steer_tau {b.steer_tau:.3f} s, "
        f"speed_tau {b.speed_tau:.3f} s, scrub {b.scrub:.3f}, scrub_lat {b.scrub_lat:.4f}, "
        f"c_speed_inv {b.c_speed_inv:.3f}, heading_c4 {b.heading_c4:.3f}, heading_s4 {b.heading_s4:.3f}.",
        "",
        "| sequence | v0 (m/s) | speed scale | PyBullet travelled (m) | position error (cm) | yaw error (rad) | unfitted defaults (cm) |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"Designed sequences: median {np.median(err) * 100:.1f} cm, {np.mean(err < 0.1) * 100:.0f} % within 10 cm, "
        f"max {err.max() * 100:.1f} cm. Random held actions (32 rollouts, not the fit's): median "
        f"{np.median(rerr) * 100:.1f} cm, p90 {np.percentile(rerr, 90) * 100:.1f} cm, max {rerr.max() * 100:.1f} cm. "
        f"The fit's mix (64 rollouts, not the fit's: random held actions and randomised transients, half "
        f"from a random heading): median {np.median(herr) * 100:.1f} cm, p90 {np.percentile(herr, 90) * 100:.1f} cm, "
        f"max {herr.max() * 100:.1f} cm.",
        "",
        "Closed loop on the racetrack (no traffic): a scripted lidar gap follower (throttle 0.7, steer",
        "towards the widest far opening) drives each backend on its own scans from the same start:",
        "",
        "| speed scale | PyBullet contact at step | fast contact at step | max position difference before (cm) | over (s) |",
        "|---|---|---|---|---|",
        *cl_rows,
        "",
        f"Lidar, wall ranges at 24 random racetrack poses ({wr.size} rays): median |difference| "
        f"{np.median(wr) * 100:.3f} cm, {np.mean(wr < 0.02) * 100:.1f} % within 2 cm, max {wr.max() * 100:.1f} cm.",
    ])


def write_report(markdown: str, doc: Path = Path("docs/training-env.md")) -> Path:
    """Replace the parity section (between ``<!-- parity -->`` markers) of the env doc."""
    text = doc.read_text()
    pattern = re.compile(r"<!-- parity -->.*?<!-- /parity -->", re.S)
    body = ("<!-- parity -->\n_Generated by `python -m racecav.training.fit_bicycle --report`._\n\n"
            + markdown.strip() + "\n<!-- /parity -->")
    doc.write_text(pattern.sub(lambda _m: body, text) if pattern.search(text) else text.rstrip() + "\n\n" + body + "\n")
    return doc


def write_bicycle(car_name: str, b: BicycleParams, stats: dict) -> Path:
    """Rewrite the ``[bicycle]`` section (the last section) of the car file."""
    path = CARS_DIR / f"{car_name}.toml"
    text = path.read_text()
    i = text.index("[bicycle]")
    j = text.rfind("\n# ---", 0, i)
    head = text[: j + 1] if j >= 0 else text[:i]
    lines = [
        "# --- Fitted single-track model for the fast backend (written by training/fit_bicycle.py) ---",
        f"# Fit: {stats['sequences']} PyBullet rollouts of {stats['horizon_s']:.1f} s, random held actions"
        " and transients;"
        f" position RMSE {stats['rmse_before']:.3f} -> {stats['rmse_after']:.3f} m,",
        f"# final error median {stats['final_err_median_after']:.3f} m, p90 {stats['final_err_p90_after']:.3f} m;"
        f" held-out sequences: median {stats['heldout_final_err_median']:.3f} m,"
        f" p90 {stats['heldout_final_err_p90']:.3f} m.",
        "# Single-track model (sim/fast_kernels.py integrate): CoG lf/lr from the axles of an",
        "# effective wheelbase lf + lr, yaw inertia iz, cornering stiffness coefficients c_sf/c_sr",
        "# (mu fixed) scaled by 1 + c_speed_inv (1/v - 1), steering lag (PyBullet's joint, not fitted) and",
        "# speed lag, speed loss in turns scrub * tan(delta)^2 + scrub_lat * |lateral acceleration|, and",
        "# PyBullet's heading-dependent grip (heading_c4, heading_s4: period 90 deg of yaw).",
        "[bicycle]",
    ]
    for name, val in b.model_dump().items():
        lines.append(f"{name} = {str(val).lower() if isinstance(val, bool) else repr(round(val, 5))}")
    path.write_text(head + "\n".join(lines) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--car", default="slash")
    ap.add_argument("--sequences", type=int, default=256)
    ap.add_argument("--steps", type=int, default=30, help="control steps per rollout (0.1 s each)")
    ap.add_argument("--iters", type=int, default=600, help="Nelder-Mead iterations per restart")
    ap.add_argument("--restarts", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--write", action="store_true", help="store the result in the car file")
    ap.add_argument("--report", action="store_true",
                    help="no fit: measure parity with the car file's model into docs/training-env.md")
    args = ap.parse_args(argv)
    car = load_car(args.car)
    if args.report:
        md = parity_report(car)
        print(md)
        print("wrote", write_report(md))
        return 0
    fitted, stats = fit(car, args.sequences, args.steps, args.seed, args.iters, args.restarts)
    print({k: round(v, 4) if isinstance(v, float) else v for k, v in stats.items()})
    print(fitted)
    if args.write:
        print("wrote", write_bicycle(args.car, fitted, stats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
