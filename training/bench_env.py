"""``racecav bench env``: env-steps per second of the fast backend against PyBullet.

The fast backend (FastWorld, numba) runs the 16-car racetrack with the lidar of EVERY car (the
obstacle cars' racing policy observes too) on 1 process and on 2 processes at once (one batch of
worlds each; the machine has 2 cores); the PyBullet backend runs the same world with all lidars,
in the same run, and the ratio is reported. Also: the training configuration (centerline traffic,
agent lidar only) through the SB3 VecEnv adapter, and PyBullet with the agent's lidar only.
Targets (issue 4): >= 5,000 env-steps/s per core and >= 80x PyBullet all-lidar.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time

import numpy as np

from racecav.common.bench import dump_json, summarize, table, write_section


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=6.0, help="timed seconds per measurement")
    p.add_argument("--n-envs", type=int, default=64, help="worlds per fast batch")
    p.add_argument("--bullet-seconds", type=float, default=6.0, help="timed seconds for PyBullet")


def _windows(step_fn, seconds: float, per_step: int, window: float = 0.5) -> list[float]:
    """Call step_fn repeatedly for ``seconds``; env-steps/s of each ``window``-second slice."""
    rates, t_end = [], time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        t0, n = time.perf_counter(), 0
        while time.perf_counter() - t0 < window:
            step_fn()
            n += per_step
        rates.append(n / (time.perf_counter() - t0))
    return rates


def fast_all_lidar(n_envs: int, seconds: float, seed: int = 0, parallel: bool = False) -> list[float]:
    """FastWorld, 15 obstacle cars + agent, lidar on every car; collided worlds reset."""
    from racecav.services.sim.fast_world import FastWorld

    fw = FastWorld(n_envs=n_envs, n_obstacles=15, obstacle_lidar=True, seed=seed, parallel=parallel)
    fw.reset()
    rng = np.random.default_rng(seed)
    acts = np.stack([rng.uniform(0, 1, (256, n_envs)), rng.uniform(-0.3, 0.3, (256, n_envs))], -1)
    k = [0]

    def step():
        _, _, col, _ = fw.step(acts[k[0] % 256])
        k[0] += 1
        if col.any():
            fw.reset_worlds(col)

    for _ in range(20):  # warm-up (JIT from the cache)
        step()
    return _windows(step, seconds, n_envs)


def fast_vecenv(n_envs: int, seconds: float, seed: int = 0) -> list[float]:
    """The training configuration: FastVecEnv (centerline traffic, agent lidar only)."""
    from racecav.training.vec_env import FastVecEnv

    venv = FastVecEnv(n_envs=n_envs, seed=seed)
    venv.reset()
    rng = np.random.default_rng(seed)
    acts = np.stack([rng.uniform(0, 1, (256, n_envs)), rng.uniform(-0.3, 0.3, (256, n_envs))], -1)
    k = [0]

    def step():
        venv.step(acts[k[0] % 256])
        k[0] += 1

    for _ in range(20):
        step()
    return _windows(step, seconds, n_envs)


def _worker(n_envs: int, seconds: float, seed: int, barrier, queue) -> None:
    from racecav.services.sim.fast_world import FastWorld

    FastWorld(n_envs=1, n_obstacles=15, obstacle_lidar=True).reset()  # load the JIT cache first
    barrier.wait()
    queue.put(fast_all_lidar(n_envs, seconds, seed))


def fast_two_processes(n_envs: int, seconds: float) -> list[list[float]]:
    """Two processes, each with its own batch, timed over the same wall-clock window."""
    ctx = mp.get_context("spawn")
    barrier, queue = ctx.Barrier(2), ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(n_envs, seconds, i, barrier, queue)) for i in range(2)]
    for p in procs:
        p.start()
    out = [queue.get(timeout=seconds + 300) for _ in procs]
    for p in procs:
        p.join()
    return out


def bullet(seconds: float, lidar_all: bool, seed: int = 0) -> list[float]:
    """PyBullet racetrack, 15 obstacle cars + agent (one world), random agent actions."""
    from racecav.services.sim.bullet_world import BulletWorld

    rng = np.random.default_rng(seed)
    with BulletWorld("racetrack", lidar_all=lidar_all, n_obstacles=15, seed=seed) as bw:
        bw.reset()

        def step():
            _, _, col, _ = bw.step(np.array([[rng.uniform(0, 1), rng.uniform(-0.3, 0.3)]]))
            if col[0]:
                bw.reset()

        for _ in range(5):
            step()
        return _windows(step, seconds, 1, window=1.0)


def run(args: argparse.Namespace, cfg) -> int:
    import os

    n, sec = args.n_envs, args.seconds
    load_before = os.getloadavg()[0]
    print(f"fast, 1 process, {n} worlds x 16 cars, all lidars ...", flush=True)
    f1 = summarize(fast_all_lidar(n, sec))
    print("fast, 1 process, lidar on numba threads ...", flush=True)
    fp = summarize(fast_all_lidar(n, sec, parallel=True))
    print("fast, 2 processes ...", flush=True)
    two = fast_two_processes(n, sec)
    f2 = summarize([sum(r) for r in zip(*two)])
    per_proc = [summarize(r)["median"] for r in two]
    print("fast VecEnv, training configuration ...", flush=True)
    fv = summarize(fast_vecenv(n, sec))
    print("PyBullet, all lidars / agent lidar ...", flush=True)
    b_all = summarize(bullet(args.bullet_seconds, True))
    b_one = summarize(bullet(args.bullet_seconds, False))
    ratio = f1["median"] / b_all["median"]
    results = {"fast_1proc_all_lidar": f1, "fast_1proc_all_lidar_numba_threads": fp, "fast_2proc_all_lidar_total": f2,
               "fast_vecenv_training_config": fv, "bullet_all_lidar": b_all,
               "bullet_agent_lidar": b_one, "ratio_fast_1proc_vs_bullet_all_lidar": ratio,
               "fast_2proc_per_process_median": per_proc, "load_average_1min_before": load_before,
               "n_envs": n, "targets": {"per_core": 5000, "ratio": 80}}
    rows = [
        [f"fast, 1 process ({n} worlds x 16 cars, every car's lidar)", f"{f1['median']:,.0f}", f"{f1['min']:,.0f}", ">= 5,000"],
        [f"fast, 1 process, lidar on numba's threads (`parallel=True`)", f"{fp['median']:,.0f}", f"{fp['min']:,.0f}", ""],
        [f"fast, 2 processes together (total; each: {per_proc[0]:,.0f} / {per_proc[1]:,.0f})",
         f"{f2['median']:,.0f}", f"{f2['min']:,.0f}", ">= 10,000"],
        [f"fast VecEnv, training config (centerline traffic, agent lidar)", f"{fv['median']:,.0f}", f"{fv['min']:,.0f}", ""],
        ["PyBullet, 16 cars, every car's lidar", f"{b_all['median']:,.1f}", f"{b_all['min']:,.1f}", ""],
        ["PyBullet, 16 cars, agent lidar only", f"{b_one['median']:,.1f}", f"{b_one['min']:,.1f}", ""],
    ]
    md = table(rows, ["backend", "env-steps/s (median)", "min", "target"])
    md += (f"\n\nRatio fast (1 process) / PyBullet (all lidars): **{ratio:,.0f}x** (target >= 80x). "
           f"Rates are medians over 0.5 s windows ({sec:g} s per fast measurement); one env-step is "
           f"one 0.1 s control period of one world (4 physics substeps, contacts every substep, "
           f"lidar at the end). The 2-core machine is shared with other work (1-minute load "
           f"average {load_before:.2f} before the run): the 2-process total is bounded by what the "
           f"cores had free.")
    print(md)
    dump_json(args.json, results)
    if not args.no_doc:
        write_section("env", "racecav bench env", md)
    return 0
