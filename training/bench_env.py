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


def _windows(step_fn, seconds: float, per_step: int, window: float = 0.5) -> dict:
    """Call step_fn repeatedly for ``seconds``; env-steps per wall-clock second and per CPU
    second of this process (all its threads) of each ``window``-second slice. On a shared
    machine the CPU rate is what a core delivers; the wall rate is what this run got."""
    wall, cpu = [], []
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        t0, c0, n = time.perf_counter(), time.process_time(), 0
        while time.perf_counter() - t0 < window:
            step_fn()
            n += per_step
        wall.append(n / (time.perf_counter() - t0))
        cpu.append(n / max(time.process_time() - c0, 1e-9))
    return {"wall": wall, "cpu": cpu}


def fast_all_lidar(n_envs: int, seconds: float, seed: int = 0, parallel: bool = False) -> dict:
    """FastWorld, 15 obstacle cars + agent, lidar on every car; collided worlds reset."""
    from racecav.sim.fast_world import FastWorld

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


def fast_vecenv(n_envs: int, seconds: float, seed: int = 0) -> dict:
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
    from racecav.sim.fast_world import FastWorld

    FastWorld(n_envs=1, n_obstacles=15, obstacle_lidar=True).reset()  # load the JIT cache first
    barrier.wait()
    queue.put(fast_all_lidar(n_envs, seconds, seed))


def fast_two_processes(n_envs: int, seconds: float) -> list[dict]:
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


def bullet(seconds: float, lidar_all: bool, seed: int = 0) -> dict:
    """PyBullet racetrack, 15 obstacle cars + agent (one world), random agent actions."""
    from racecav.sim.bullet_world import BulletWorld

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


def _row(name: str, r: dict, target: str = "") -> list:
    w, c = summarize(r["wall"]), summarize(r["cpu"])
    fmt = (lambda v: f"{v:,.1f}") if w["median"] < 1000 else (lambda v: f"{v:,.0f}")
    return [name, fmt(w["median"]), fmt(c["median"]), target]


def run(args: argparse.Namespace, cfg) -> int:
    import os

    n, sec = args.n_envs, args.seconds
    load_before = os.getloadavg()[0]
    print(f"fast, 1 process, {n} worlds x 16 cars, all lidars ...", flush=True)
    f1 = fast_all_lidar(n, sec)
    print("fast, 1 process, lidar on numba threads ...", flush=True)
    fp = fast_all_lidar(n, sec, parallel=True)
    print("fast, 2 processes ...", flush=True)
    two = fast_two_processes(n, sec)
    f2 = {k: [sum(r) for r in zip(two[0][k], two[1][k])] for k in ("wall", "cpu")}
    print("fast VecEnv, training configuration ...", flush=True)
    fv = fast_vecenv(n, sec)
    print("PyBullet, all lidars / agent lidar ...", flush=True)
    b_all = bullet(args.bullet_seconds, True)
    b_one = bullet(args.bullet_seconds, False)
    med = lambda r, k: summarize(r[k])["median"]  # noqa: E731
    ratio = med(f1, "wall") / med(b_all, "wall")
    ratio_cpu = med(f1, "cpu") / med(b_all, "cpu")
    results = {name: {k: summarize(v) for k, v in r.items()} for name, r in (
        ("fast_1proc_all_lidar", f1), ("fast_1proc_all_lidar_numba_threads", fp),
        ("fast_2proc_all_lidar_total", f2), ("fast_vecenv_training_config", fv),
        ("bullet_all_lidar", b_all), ("bullet_agent_lidar", b_one))}
    results.update({"ratio_fast_1proc_vs_bullet_all_lidar": ratio, "ratio_per_cpu_second": ratio_cpu,
                    "fast_2proc_per_process_median": [med(r, "wall") for r in two],
                    "load_average_1min_before": load_before, "n_envs": n,
                    "targets": {"per_core": 5000, "ratio": 80}})
    rows = [
        _row(f"fast, 1 process ({n} worlds x 16 cars, every car's lidar)", f1, ">= 5,000 per core"),
        _row("fast, 1 process, lidar on numba's threads (`parallel=True`)", fp),
        _row(f"fast, 2 processes together (each: {med(two[0], 'wall'):,.0f} / {med(two[1], 'wall'):,.0f})", f2),
        _row("fast VecEnv, training config (centerline traffic, agent lidar)", fv),
        _row("PyBullet, 16 cars, every car's lidar", b_all),
        _row("PyBullet, 16 cars, agent lidar only", b_one),
    ]
    md = table(rows, ["backend", "env-steps/s (wall clock)", "env-steps per CPU-second", "target"])
    md += (f"\n\nRatio fast (1 process) / PyBullet (all lidars): **{ratio:,.0f}x** wall clock, "
           f"**{ratio_cpu:,.0f}x** per CPU-second (target >= 80x). Medians over 0.5 s windows "
           f"({sec:g} s per fast measurement); one env-step is one 0.1 s control period of one world "
           f"(4 physics substeps, contacts, lidar). The 2-core machine is shared with other work "
           f"(1-minute load average {load_before:.2f} before the run): wall-clock rates are what "
           f"this run got, CPU-second rates what a core delivers (for the numba-threads row, per "
           f"CPU-second of both threads).")
    print(md)
    dump_json(args.json, results)
    if not args.no_doc:
        write_section("env", "racecav bench env", md)
    return 0
