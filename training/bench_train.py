"""``racecav bench train``: PPO samples/s of the paper's setting vs faster alternatives.

Each configuration trains from scratch for ``--seconds`` of wall time on the fast world (racing
stage: 0 obstacles, and optionally the overtake stage with the policy-driven traffic) and reports
samples/s and the share of time spent in the PPO update. The trade-off is discussed in
docs/training.md; the numbers go to docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import time

# name -> (n_envs, n_steps, batch_size, n_epochs)
CONFIGS = {
    "paper (1 env, 2048, b64, e10)": (1, 2048, 64, 10),
    "64 envs, 2048/rollout, b64, e10": (64, 32, 64, 10),
    "64 envs, 8192/rollout, b64, e10": (64, 128, 64, 10),
    "64 envs, 8192/rollout, b512, e10": (64, 128, 512, 10),
    "64 envs, 8192/rollout, b2048, e10 (fast)": (64, 128, 2048, 10),
    "64 envs, 8192/rollout, b2048, e4": (64, 128, 2048, 4),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=30.0, help="wall time per configuration")
    parser.add_argument("--n-obstacles", type=int, default=0)
    parser.add_argument("--driver", default="centerline")
    parser.add_argument("--only", help="substring filter on configuration names")


def measure(n_envs, n_steps, batch, epochs, seconds, n_obstacles=0, driver="centerline") -> dict:
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    from racecav.training.vec_env import FastVecEnv

    torch.set_num_threads(1)
    venv = VecNormalize(VecMonitor(FastVecEnv(n_envs=n_envs, n_obstacles=n_obstacles, driver=driver, seed=0)))
    model = PPO("MlpPolicy", venv, n_steps=n_steps, batch_size=batch, n_epochs=epochs, seed=0,
                device="cpu", policy_kwargs=dict(net_arch=[64, 64], activation_fn=torch.nn.Tanh))
    t_update = 0.0
    train = model.train

    def timed_train():
        nonlocal t_update
        t = time.perf_counter()
        train()
        t_update += time.perf_counter() - t

    model.train = timed_train
    rollout = n_envs * n_steps
    model.learn(rollout)  # warm-up (numba compile, first update)
    t_update = 0.0
    n0, t0 = model.num_timesteps, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        model.learn(rollout, reset_num_timesteps=False)
    dt = time.perf_counter() - t0
    n = model.num_timesteps - n0
    return {"samples_per_s": n / dt, "update_share": t_update / dt, "samples": n,
            "grad_steps_per_1k_samples": 1000 * epochs / batch}


def run(args, cfg) -> int:
    from racecav.common.bench import dump_json, write_section

    rows = {}
    for name, (e, s, b, ep) in CONFIGS.items():
        if args.only and args.only not in name:
            continue
        r = measure(e, s, b, ep, args.seconds, args.n_obstacles, args.driver)
        rows[name] = r
        print(f"{name:45s} {r['samples_per_s']:8.0f} samples/s  update {100 * r['update_share']:4.0f} %  "
              f"{r['grad_steps_per_1k_samples']:6.1f} grad steps/1k samples", flush=True)
    dump_json(args.json, rows)
    if not args.no_doc:
        md = ["| configuration | samples/s | time in update | gradient steps per 1k samples |",
              "|---|---|---|---|"]
        md += [f"| {k} | {v['samples_per_s']:.0f} | {100 * v['update_share']:.0f} % | "
               f"{v['grad_steps_per_1k_samples']:.1f} |" for k, v in rows.items()]
        md.append(f"\nFast world, {args.n_obstacles} obstacle cars (driver {args.driver}), "
                  f"{args.seconds:.0f} s per configuration, 1 torch thread, shared 2-core machine.")
        write_section("train", f"racecav bench train --seconds {args.seconds:g} --n-obstacles {args.n_obstacles}",
                      "\n".join(md))
    return 0
