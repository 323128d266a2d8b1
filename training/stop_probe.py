"""``racecav train stop-probe``: what the stop-and-look teacher (``--expert stop``) or the yield
teacher (``--expert yield``) passes, driven by its own labels in the fast world, beside the
non-evading references (straight at 1 m/s and at full throttle) on the same seeds.

Every world drives one episode of the scenario files (selection seed); the teacher's families are
driven by its labels (training/mirror.MirrorTeacher, relabel stop: brake before the crossing,
wait while a car in the ego's scan is in it or closing on it, then straight on; relabel yield:
the same without the stop before the crossing, following a car ahead in the lane and steering
round one that blocks it), and where the labels end (past the crossing) on along the road at full
throttle (its tracking steer); every other family straight at full throttle. It answers whether
a manoeuvre passes a family, before a policy is trained to it.
"""

from __future__ import annotations


def add_subcommands(sub) -> None:
    p = sub.add_parser("stop-probe", help="success of the stop-and-look (--expert stop) or yield teacher driven by its own "
                       "labels in the fast world, per family, beside the non-evading references")
    p.add_argument("--scenarios", required=True, help="suite NAME (train split), folder or scenario files")
    p.add_argument("--families", default="cross-left,cross-right", help="the families the teacher drives "
                   "(as --mirror-families); the others drive straight at full throttle")
    p.add_argument("--expert", choices=("stop", "yield"), default="stop", help="the teacher: stop (brake "
                   "before every crossing, then look) or yield (brake only while a car in the scan is busy)")
    p.add_argument("--n", type=int, default=1024, help="fast worlds (one episode each)")
    p.add_argument("--seed", type=int, help="default: select's selection seed")
    p.set_defaults(stage="stop-probe")


def stop_probe(scenarios: str, families: list[str], n: int, seed: int, relabel: str = "stop") -> dict[str, dict[str, tuple[int, float]]]:
    """{driver: {family: (episodes, success)}}: the teacher (``relabel`` stop or yield), then the non-evading
    references (select.reference_drivers), on the same seeds (so the same files per world)."""
    import numpy as np

    from racecav.common.config import EnvConfig
    from racecav.training.expert import tracking_steer
    from racecav.training.mirror import MirrorTeacher
    from racecav.training.select import ConstantAction, reference_drivers
    from racecav.training.vec_env import FastVecEnv

    # the teacher needs the brake; its "in the ego's scan" is the shipped avoid's (wide) view
    cfg = EnvConfig(scenarios=scenarios, scenario_share=1.0, lidar="wide", obs_stack=1, brake_below=-0.5)
    out = {}
    teacher_name = {"stop": "stop and look", "yield": "yield"}[relabel]
    for name, driver in {teacher_name: None, **reference_drivers()}.items():
        env = FastVecEnv(n_envs=n, config=cfg, seed=seed)
        obs = env.reset()
        teacher = MirrorTeacher(ConstantAction(1.0), env, families, relabel=relabel) if driver is None else None
        fam = np.concatenate([np.array(w.scenario_families)[w.scenario_index] if w.actors is not None
                              else np.full(w.n_envs, "traffic") for w in env.worlds])
        done, ok = np.zeros(n, bool), np.zeros(n, bool)
        while not done.all():
            if teacher:  # its families: its labels, and where it gives none, on along the road
                act, mask = teacher.labels(obs)
                free = teacher.in_families() & ~mask
                if free.any():
                    act[free, 1] = np.concatenate([tracking_steer(w) for w in env.worlds])[free]
            else:
                act = driver(obs)
            obs, _r, d, infos = env.step(act.astype(np.float32))
            for i in np.flatnonzero(d & ~done):
                ok[i] = infos[i].get("is_success", False)
            done |= d
        env.close()
        out[name] = {f: (int((fam == f).sum()), float(ok[fam == f].mean())) for f in sorted(set(fam.tolist()))}
    return out


def run(args, cfg) -> int:
    import torch

    from racecav.training.select import SELECT_SEED

    torch.set_num_threads(1)
    if args.n < 1:
        raise SystemExit("racecav train stop-probe: --n must be >= 1")
    families = [f.strip() for f in args.families.split(",") if f.strip()]
    try:
        res = stop_probe(args.scenarios, families, args.n, SELECT_SEED if args.seed is None else args.seed, args.expert)
    except (ValueError, FileNotFoundError) as e:  # the teacher names its training flag
        raise SystemExit(f"racecav train stop-probe: {str(e).replace('--mirror-families', '--families')}") from None
    print(f"{args.expert} teacher on {args.scenarios} (it drives {', '.join(families)}; the rest straight at full "
          "throttle), beside the non-evading references on the same seeds")
    print("| family | episodes | " + " | ".join(res) + " |\n|---|---:|" + "---:|" * len(res))
    for f, (k, _s) in next(iter(res.values())).items():
        print(f"| {f} | {k} | " + " | ".join(f"{100 * r[f][1]:.0f} %" for r in res.values()) + " |")
    return 0
