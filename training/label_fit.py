"""``racecav train label-fit``: does a policy drive straight before a car is in view?

The ``--expert hold`` labels (training/mirror.py) say: before any car has returned a ray of the
ego's scan, track the ego's road (training/expert.tracking_steer). This measures how well a
policy follows them, by the ego's distance to the conflict point: at every step of one episode
in each of ``n`` fast worlds of the scenario files, while no car has been in view and the ego is
short of the conflict point, the policy's steering action (clipped to [-1, 1]) is compared with
the tracking steer. Two approaches, on the same seeds:

- held: the hold-until-seen override drives (training/vec_env.FastVecEnv, as in training with
  ``--hold-until-seen``; ``--hold-through`` files held to the conflict point), so the states are
  the ones the labels were fitted on;
- own: the policy drives, as it ships.

A policy that meets the labels where it was trained but not where it drives has a shift problem;
one that misses them on the held approach too has not fitted them. Scenario convention as in
probe.py: the conflict point is at x = 0 on the ego's road, the ego starts at x < 0 heading +x.
"""

from __future__ import annotations

from pathlib import Path

BANDS = ((-99.0, -3.0), (-3.0, -2.0), (-2.0, 0.0))
"""Ego x bands (m to the conflict point) of the table."""
AGREE = 0.1
"""|policy steer - tracking steer| (action units) within which a step counts as following."""


def add_subcommands(sub) -> None:
    p = sub.add_parser("label-fit", help="how well a policy follows the straight labels of --expert hold before a car "
                       "is in view, by distance to the conflict point: on the held approach and on its own")
    p.add_argument("--policy", default="avoid", help="shipped policy name, .npz, or a run's checkpoint .zip (with the run's settings)")
    p.add_argument("--scenarios", required=True, help="suite NAME (train split), folder or scenario file")
    p.add_argument("--hold-through", default="", help="families held to the conflict point on the held approach "
                   "(as train overtake --hold-through)")
    p.add_argument("--n", type=int, default=256, help="fast worlds (one episode each)")
    p.add_argument("--steps", type=int, default=60, help="control steps per episode")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(stage="label-fit")


def label_fit(policy, scenarios: str, hold_through: str = "", n: int = 256, steps: int = 60,
              seed: int = 0) -> dict[str, dict[tuple[float, float], tuple[int, float]]]:
    """{"held" | "own": {band: (steps, share within AGREE)}} (share NaN where a band has no step)."""
    import numpy as np

    from racecav.training.expert import latch_seen, tracking_steer
    from racecav.training.select import policy_view_env
    from racecav.training.vec_env import FastVecEnv

    cfg = policy_view_env(policy, scenarios)
    out = {}
    for mode in ("held", "own"):
        held = mode == "held"
        env = FastVecEnv(n_envs=n, config=cfg, scenario_share=1.0, seed=seed, hold_until_seen=held,
                         hold_through=hold_through if held else "")
        obs = env.reset()
        seen = [np.zeros(w.n_envs, bool) for w in env.worlds]
        ended = np.zeros(n, bool)  # one episode per world: later ones are not counted
        errs: dict[tuple[float, float], list[float]] = {b: [] for b in BANDS}
        for _ in range(steps):
            act = policy(obs)
            parts = []
            for k, w in enumerate(env.worlds):
                seen[k] = latch_seen(w, seen[k], np.arange(w.n_envs))
                x = w.x[:, 0]
                parts.append((~seen[k] & (x < 0.0) & (w.time > 0), x, tracking_steer(w)))
            pre, x, track = (np.concatenate(v) for v in zip(*parts))
            pre &= ~ended
            err = np.abs(np.clip(act[:, 1], -1.0, 1.0) - track)
            for b in BANDS:
                m = pre & (x >= b[0]) & (x < b[1])
                errs[b] += err[m].tolist()
            obs, _r, done, _info = env.step(act)
            ended |= done
            if ended.all():
                break
        env.close()
        out[mode] = {b: (len(v), float(np.mean(np.array(v) < AGREE)) if v else float("nan")) for b, v in errs.items()}
    return out


def run(args, cfg) -> int:
    import torch

    from racecav.training.select import named_policy

    torch.set_num_threads(1)
    if args.n < 1 or args.steps < 1:
        raise SystemExit("racecav train label-fit: --n and --steps must be >= 1")
    try:
        res = label_fit(named_policy(args.policy), args.scenarios, args.hold_through, args.n, args.steps, args.seed)
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"racecav train label-fit: {e}") from None
    name = lambda b: f"x < {b[1]:g} m" if b[0] < -90 else f"{b[0]:g} <= x < {b[1]:g} m"  # noqa: E731
    print(f"{args.policy} on {args.scenarios}: steps before a car is in view within {AGREE} of the tracking steer "
          f"(steps counted)")
    print("| approach | " + " | ".join(name(b) for b in BANDS) + " |\n|---|" + "---:|" * len(BANDS))
    for mode, bands in res.items():
        print(f"| {mode} | " + " | ".join(f"{100 * s:.0f} % ({c})" if c else "-" for c, s in bands.values()) + " |")
    return 0
