"""``racecav train probe``: how early does a policy's view tell two timings of the same conflict apart?

A policy drives its own view in the fast world through the scenario files of two sources (suites,
folders or files; by default the paper-timed and the conflict-timed cars crossing from the left).
At the first step its ego is within each distance of the conflict point, the newest scan (and the
scan ``stride`` steps older) is kept. A fresh MLP of the policy's size (2 x 64 tanh) is then fitted
to tell the two sources apart from those scans, and its held-out accuracy says how much of the
difference the view holds at that distance (0.5: none; it is a lower bound, the probe sees only
the episodes run). Episodes are matched on the ego's speed (the overlap of the two sources' 10-90 %
ranges) and balanced, and "speed alone" is the best accuracy of a speed threshold, so a gap the
speed explains is not read as a view difference. The policy's own turn at each distance (mean yaw)
says when it commits. Beside it, the privileged planner (training/expert.py), held straight on
its road at full throttle until its ego is within each distance and free from there, says
whether a decision that late can still pass both sources (``--late-n`` worlds per cell), and
held straight until k control periods after a car is first in its ego's scan (``--seen-delays``),
what a policy that answers only what it sees could pass.
``--out X.md`` writes the tables (docs/training.md embeds
training/checkpoints/probe-cross-left.md), ``--out X.csv`` the probe rows.

Scenario convention: the conflict point lies on the ego's road at x = 0, the ego starts at x < 0
heading +x (the paper's scenarios and the generated crossing and head-on families).
"""

from __future__ import annotations

import csv
from pathlib import Path

HIDDEN = 64
"""The probe's width: the shipped policies' (SB3 MlpPolicy net_arch [64, 64], tanh)."""


def add_subcommands(sub) -> None:
    p = sub.add_parser("probe", help="how early a policy's view tells two scenario sources apart "
                       "(e.g. paper-timed vs conflict-timed crossings): a supervised probe per distance and scan stride")
    p.add_argument("--policy", default="avoid", help="shipped policy name, .npz, or a run's checkpoint .zip (with the run's settings): it drives (its own view)")
    p.add_argument("--sources", default="paper-timed,conflicts",
                   help="two scenario sources, comma-separated: suite NAME (train split), folder or file")
    p.add_argument("--family", default="cross-left", help="only scenario files whose name starts with this ('' = all)")
    p.add_argument("--n", type=int, default=8192, help="fast worlds per source (one episode each)")
    p.add_argument("--distances", default="3,2.5,2,1.5", help="ego distances to the conflict point (m)")
    p.add_argument("--strides", default="0,1,2,4,8",
                   help="probe views: 0 = the newest scan alone, s = it and the scan s control periods older")
    p.add_argument("--late-n", type=int, default=256,
                   help="worlds per source and distance for the planner held straight until that distance (0: skip)")
    p.add_argument("--seen-delays", default="0,1,2,4",
                   help="control periods after a car is first in the held-straight ego's scan at which the planner "
                        "is freed (with --late-n; '' to skip)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, help="also write the tables (X.md) or the probe rows (X.csv)")
    p.set_defaults(stage="probe")


def _floats(text: str, what: str) -> list[float]:
    try:
        out = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"racecav train probe: {what}: expected comma-separated numbers, got {text!r}") from None
    if not out:
        raise SystemExit(f"racecav train probe: {what}: empty")
    return out


def collect(policy, source: str, family: str, n: int, distances, strides, seed: int) -> dict:
    """Drive ``policy`` through one episode in each of ``n`` fast worlds of ``source``; per distance:
    the probe views (``strides``), the ego speed and yaw there, and each episode's success."""
    import numpy as np

    from racecav.training.select import policy_view_env
    from racecav.training.vec_env import FastVecEnv

    # seen as the policy sees it (its view, stack, stride and brake); a reference driver
    # (training/select.ConstantAction) has the paper's view
    env = FastVecEnv(n_envs=n, config=policy_view_env(policy, source), seed=seed)
    obs = env.reset()
    names = np.concatenate([[w.scenarios[k].name for k in w.scenario_index] for w in env.worlds])
    keep = np.array([str(x).startswith(family) for x in names])
    if not keep.any():
        raise SystemExit(f"racecav train probe: no scenario of {source!r} starts with {family!r}")
    rays = env.world.spec.n_rays
    depth = max(strides) + 1
    hist = np.repeat(obs[:, None, :rays], depth, axis=1)  # newest scan first
    views = {(d, s): np.full((n, rays if s == 0 else 2 * rays), np.nan, np.float32) for d in distances for s in strides}
    speed = {d: np.full(n, np.nan) for d in distances}
    yaw = {d: np.full(n, np.nan) for d in distances}
    done, success = np.zeros(n, bool), np.zeros(n, bool)
    while not done.all():
        st = np.concatenate([w.agent_state() for w in env.worlds])  # x, y, yaw, v
        for d in distances:
            m = (st[:, 0] >= -d) & np.isnan(speed[d]) & ~done
            for s in strides:
                views[(d, s)][m] = hist[m, 0] if s == 0 else np.concatenate([hist[m, 0], hist[m, s]], axis=1)
            speed[d][m], yaw[d][m] = st[m, 3], st[m, 2]
        obs, _r, dn, infos = env.step(policy(obs))
        hist = np.concatenate([obs[:, None, :rays], hist[:, :-1]], axis=1)
        for i in np.flatnonzero(dn & ~done):
            success[i] = infos[i].get("is_success", False)
        done |= dn
    return {"views": {k: v[keep] for k, v in views.items()}, "speed": {d: v[keep] for d, v in speed.items()},
            "yaw": {d: v[keep] for d, v in yaw.items()}, "success": success[keep]}


def _held_planner(source: str, family: str, n: int, seed: int, make_release) -> tuple[float, float]:
    """The privileged planner held straight (tracking its road at full throttle) in ``n`` worlds of
    each world geometry of the source's files, each world free once its release says so:
    ``make_release(fw)`` gives, per FastWorld, a function of the mask of worlds still held that
    returns a bool mask over the worlds. Returns (success, median distance of the ego to the
    conflict point when it was freed)."""
    import numpy as np

    from racecav.common.scenario import load_scenario, scenario_sources
    from racecav.sim.fast_world import FastWorld

    scs = [sc for sc in (load_scenario(f) for f, _fam in scenario_sources(source, "train")) if sc.name.startswith(family)]
    if not scs:
        raise SystemExit(f"racecav train probe: no scenario of {source!r} starts with {family!r}")
    success, freed_at = [], []
    for k, world in enumerate(sorted({sc.world for sc in scs})):  # one FastWorld per world geometry
        fw = FastWorld(n_envs=n, scenarios=[sc for sc in scs if sc.world == world], seed=seed + k)
        ok, where = held_outcomes(fw, make_release)
        success.append(ok)
        freed_at.append(where)
    freed = np.concatenate(freed_at)
    return float(np.concatenate(success).mean()), float(np.nanmedian(freed)) if np.isfinite(freed).any() else float("nan")


def held_outcomes(fw, make_release, on_ended=None):
    """Reset the scenario FastWorld ``fw`` and drive every world once with the held planner (see
    _held_planner): (success per world, the ego's distance to the conflict point when it was
    freed; NaN: never freed). ``on_ended(k)`` hears of the k worlds whose episode ended at a step."""
    import numpy as np

    from racecav.training.expert import Expert, tracking_steer

    n = fw.n_envs
    fw.reset()
    planner, release = Expert(fw), make_release(fw)
    late, ended, ok = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
    where = np.full(n, np.nan)
    while not ended.all():
        now = ~late & ~ended & release(~late)
        where[now] = -fw.agent_state()[now, 0]
        late |= now
        a = np.stack([np.ones(n), tracking_steer(fw)], axis=1)
        if late.any():
            a[late] = planner.act()[late]
        fw.step(a)
        over = ~ended & (fw.contact() | (fw.time >= fw.time_limit - 1e-9))
        ok[over] = fw.success()[over]
        ended |= over
        if on_ended is not None and over.any():
            on_ended(int(over.sum()))
    return ok, where


def late_decision(source: str, family: str, n: int, distances, seed: int) -> dict[float, float]:
    """Success of the privileged planner held straight (tracking its road at full throttle) until
    its ego is within each distance of the conflict point, free from there: can a decision that
    late still pass the source's files? Distance inf: the planner from the start."""
    def within(d):
        return lambda fw: lambda held: fw.agent_state()[:, 0] >= -d

    return {d: _held_planner(source, family, n, seed, within(d))[0] for d in distances}


def seen_decision(source: str, family: str, n: int, delays, seed: int) -> dict[int, tuple[float, float]]:
    """The planner held straight as in late_decision until ``delay`` control periods after a car
    first returned a ray of its ego's scan (FastWorld.seen_by_agent), free from there (and at
    the conflict point at the latest): what a policy that must see a car, and then needs some
    scans to judge its motion, could still pass if it then drove as the planner does.
    Returns {delay: (success, median distance to the conflict point when freed)}."""
    return {k: _held_planner(source, family, n, seed, released_after_seen(k)) for k in delays}


def released_after_seen(delay: int):
    """The release of seen_decision (for _held_planner / held_outcomes): a world is freed ``delay``
    control periods after a car first returned a ray of its ego's scan, or at the conflict point."""
    import numpy as np

    def make(fw):
        periods = np.full(fw.n_envs, -1)  # since a car was first in view; -1: not yet

        def release(held):
            envs = np.flatnonzero(held & (periods < 0))
            if envs.size:
                periods[envs[fw.seen_by_agent(envs).any(axis=1)]] = 0
            out = (periods >= delay) | (fw.agent_state()[:, 0] >= 0.0)
            periods[periods >= 0] += 1
            return out
        return release
    return make


def fit_probe(x0, x1, v0, v1, seed: int = 0) -> dict:
    """Held-out accuracy of a 2 x 64 tanh MLP telling ``x0`` from ``x1`` on speed-matched, balanced
    samples (70/30 split), and of a speed threshold alone; NaN when the speeds do not overlap."""
    import numpy as np
    import torch

    rng = np.random.default_rng(seed)
    lo = max(np.nanpercentile(v0, 10), np.nanpercentile(v1, 10))
    hi = min(np.nanpercentile(v0, 90), np.nanpercentile(v1, 90))
    i0 = np.flatnonzero(np.isfinite(x0[:, 0]) & (v0 >= lo) & (v0 <= hi))
    i1 = np.flatnonzero(np.isfinite(x1[:, 0]) & (v1 >= lo) & (v1 <= hi))
    m = min(len(i0), len(i1))
    out = {"speed_lo": float(lo), "speed_hi": float(hi), "per_class": int(m)}
    if m < 20:
        return out | {"speed_alone": float("nan"), "probe_train": float("nan"), "probe_heldout": float("nan")}
    i0, i1 = rng.choice(i0, m, replace=False), rng.choice(i1, m, replace=False)
    x = np.concatenate([x0[i0], x1[i1]]).astype(np.float32)
    y = np.concatenate([np.zeros(m), np.ones(m)]).astype(np.float32)
    v = np.concatenate([v0[i0], v1[i1]])
    speed_alone = max(max(((v > t) == y).mean(), ((v <= t) == y).mean()) for t in np.unique(v))
    idx = rng.permutation(2 * m)
    tr, te = idx[: int(0.7 * len(idx))], idx[int(0.7 * len(idx)):]
    mu, sd = x[tr].mean(0), x[tr].std(0) + 1e-3  # from the training part only
    x = (x - mu) / sd
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], HIDDEN), torch.nn.Tanh(),
                              torch.nn.Linear(HIDDEN, HIDDEN), torch.nn.Tanh(), torch.nn.Linear(HIDDEN, 1))
    opt = torch.optim.Adam(net.parameters(), 1e-3, weight_decay=1e-4)
    xt, yt = torch.from_numpy(x[tr]), torch.from_numpy(y[tr])
    for _ in range(400):  # full batch: a few thousand samples
        opt.zero_grad()
        torch.nn.functional.binary_cross_entropy_with_logits(net(xt)[:, 0], yt).backward()
        opt.step()
    with torch.no_grad():
        acc = lambda i: float(((net(torch.from_numpy(x[i]))[:, 0] > 0).numpy() == y[i]).mean())  # noqa: E731
        return out | {"speed_alone": float(speed_alone), "probe_train": acc(tr), "probe_heldout": acc(te)}


def probe(args, cfg) -> int:
    import torch

    from racecav.training.select import named_policy, reference_drivers

    torch.set_num_threads(1)
    sources = [s.strip() for s in args.sources.split(",") if s.strip()]
    if len(sources) != 2:
        raise SystemExit(f"racecav train probe: --sources: expected two sources, got {sources}")
    distances = _floats(args.distances, "--distances")
    strides = [int(s) for s in _floats(args.strides, "--strides")]
    delays = [int(d) for d in _floats(args.seen_delays, "--seen-delays")] if args.seen_delays.strip() else []
    if any(d < 0 for d in delays):
        raise SystemExit("racecav train probe: --seen-delays must be >= 0")
    if any(s < 0 for s in strides) or any(d <= 0 for d in distances) or args.n < 1 or args.late_n < 0:
        raise SystemExit("racecav train probe: --strides must be >= 0, --distances > 0, --n >= 1 and --late-n >= 0")
    policy = named_policy(args.policy)
    data = [collect(policy, src, args.family, args.n, distances, strides, args.seed + 7919 * k)
            for k, src in enumerate(sources)]
    # the non-evading references on the same worlds and seeds, beside the policy's success
    for k, (src, dat) in enumerate(zip(sources, data)):
        dat["references"] = {name: float(collect(drv, src, args.family, args.n, distances[:1], [0],
                                                 args.seed + 7919 * k)["success"].mean())
                             for name, drv in reference_drivers().items()}
        dat["late"] = late_decision(src, args.family, args.late_n, [float("inf")] + distances,
                                    args.seed + 7919 * k) if args.late_n else {}
        dat["seen"] = seen_decision(src, args.family, args.late_n, delays, args.seed + 7919 * k) if args.late_n else {}
    rows = [{"distance_m": d, "stride": s, **fit_probe(data[0]["views"][(d, s)], data[1]["views"][(d, s)],
                                                      data[0]["speed"][d], data[1]["speed"][d], seed=args.seed)}
            for d in distances for s in strides]
    text = _markdown(args, sources, data, distances, rows)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        if args.out.suffix == ".md":
            args.out.write_text(text)
        else:
            with args.out.open("w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)
        print(f"wrote {args.out}")
    return 0


def _control_period() -> float:
    """The control period (s) of the fast world's car (its default, as the planners above use)."""
    from racecav.common.vehicle import load_car

    return load_car().control_period_s


def _markdown(args, sources, data, distances, rows) -> str:
    import numpy as np

    L = [f"`racecav train probe --policy {args.policy} --sources {args.sources} --family '{args.family}' --n {args.n} "
         f"--distances {args.distances} --strides {args.strides} --late-n {args.late_n} "
         f"--seen-delays '{args.seen_delays}' --seed {args.seed}`", "",
         "| source | episodes | success | " + " | ".join(f"{r}, no evasion" for r in data[0]["references"]) + " | "
         + " | ".join(f"policy's yaw at {d:g} m (deg)" for d in distances) + " |",
         "|---|---:|---:|" + "---:|" * (len(data[0]["references"]) + len(distances))]
    for src, dat in zip(sources, data):
        L.append(f"| {src} | {len(dat['success'])} | {100 * dat['success'].mean():.0f} % | "
                 + " | ".join(f"{100 * v:.0f} %" for v in dat["references"].values()) + " | "
                 + " | ".join(f"{np.degrees(np.nanmean(dat['yaw'][d])):.1f}" for d in distances) + " |")
    if data[0]["late"]:
        L += ["", f"The privileged planner, held straight at full throttle until its ego is within each distance of the "
              f"conflict point and free from there ({args.late_n} worlds per cell): success", "",
              "| source | " + " | ".join("from the start" if d == float("inf") else f"straight until {d:g} m"
                                       for d in data[0]["late"]) + " |", "|---|" + "---:|" * len(data[0]["late"])]
        for src, dat in zip(sources, data):
            L.append(f"| {src} | " + " | ".join(f"{100 * v:.0f} %" for v in dat["late"].values()) + " |")
    if data[0].get("seen"):
        period_ms = 1000 * _control_period()
        L += ["", f"The same planner held straight until k control periods ({period_ms:.0f} ms each) after a car first "
              "returned a ray of its ego's scan, free from there (at the conflict point at the latest): success, and "
              "the median distance of the ego to the conflict point when freed", "",
              "| source | " + " | ".join(f"{k} periods after first seen" for k in data[0]["seen"]) + " |",
              "|---|" + "---:|" * len(data[0]["seen"])]
        for src, dat in zip(sources, data):
            L.append(f"| {src} | " + " | ".join(f"{100 * ok:.0f} % ({d:.2f} m)" for ok, d in dat["seen"].values()) + " |")
    L += ["", "| ego to conflict point (m) | probe's view | speed band (m/s) | per class | speed alone | probe train | "
          "probe held-out |", "|---:|---|---|---:|---:|---:|---:|"]
    for r in rows:
        view = "newest scan" if r["stride"] == 0 else f"+ the scan {r['stride']} periods older"
        L.append(f"| {r['distance_m']:g} | {view} | {r['speed_lo']:.2f}-{r['speed_hi']:.2f} | {r['per_class']} | "
                 f"{r['speed_alone']:.2f} | {r['probe_train']:.2f} | {r['probe_heldout']:.2f} |")
    return "\n".join(L) + "\n"
