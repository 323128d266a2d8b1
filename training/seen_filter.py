"""``racecav train seen-filter``: a suite's train split cut down to the files a driver that answers
only what it sees can pass.

Why: row 31 (the shipped avoid) starts its left turn at an intersection before the crossing car is
in its scan. That habit wins the conflict-timed crossings from the left whose car comes out too
late for any evasion begun at first sight (the probe's seeing planner, training/probe.py, passes
77 % of the conflict suite's crossings from the left) and loses the paper-timed ones, whose car
stays hidden until a straight ego is through (docs/training.md, "When the view tells the two
timings apart"). A file no reactive driver can pass pays only for guessing; without such files in
the mix, a turn begun before anything is seen earns nothing and the paper-timed files still
charge it.

The filter drives each train file ``--draws`` times (its randomisation drawn anew each time) with
the privileged planner held straight on its road at full throttle until ``--delay`` control
periods after a car first returned a ray of its ego's scan (probe.released_after_seen), and keeps
the files it passes in at least ``--keep`` of the draws. The new suite (a folder with suite.json,
its families as in the source, the kept files copied, an empty test split) goes where
``--scenarios`` takes it; suite.json records the filter and each kept file's pass rate. The test
split and the selection seeds are not touched: the selection and the report still use the
source suites.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path


def add_subcommands(sub) -> None:
    p = sub.add_parser("seen-filter", help="write a suite holding the train files that a planner answering only "
                       "what its ego sees passes (training mix without unwinnable-by-reaction files)")
    p.add_argument("--source", required=True, help="suite NAME or folder with suite.json (its train split is filtered)")
    p.add_argument("--out", type=Path, required=True, help="folder of the new suite (e.g. runs/suites/conflicts-seen)")
    p.add_argument("--draws", type=int, default=16, help="draws of each file's randomisation")
    p.add_argument("--delay", type=int, default=2, help="control periods after first sight before the planner is freed")
    p.add_argument("--keep", type=float, default=0.75, help="keep a file passed in at least this share of its draws")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    p.set_defaults(stage="seen-filter")


def pass_rates(files: list[Path], draws: int, delay: int, seed: int, progress: bool = True) -> list[float]:
    """The seeing planner's success per file over ``draws`` draws of its randomisation (about
    1 CPU-s per 5 episodes: the conflict suite's 1400 files x 8 draws take 26 min)."""
    import numpy as np
    from tqdm import tqdm

    from racecav.common.scenario import load_scenario
    from racecav.sim.fast_world import FastWorld
    from racecav.training.probe import held_outcomes, released_after_seen

    scs = [load_scenario(f) for f in files]
    rates = np.zeros(len(files))
    bar = tqdm(total=len(files) * draws, desc="seen-filter", unit="episode", disable=not progress)
    for k, world in enumerate(sorted({sc.world for sc in scs})):  # one FastWorld per world geometry
        idx = [i for i, sc in enumerate(scs) if sc.world == world]
        fw = FastWorld(n_envs=len(idx) * draws, scenarios=[scs[i] for i in idx], seed=seed + 7919 * k)
        fw.scenario_of_env = np.repeat(np.arange(len(idx)), draws)
        ok, _where = held_outcomes(fw, released_after_seen(delay), on_ended=bar.update)
        rates[idx] = ok.reshape(len(idx), draws).mean(axis=1)
    bar.close()
    return rates.tolist()


def seen_filter(args, cfg) -> int:
    from racecav.common.scenario import open_suite

    if args.draws < 1 or args.delay < 0 or not 0.0 <= args.keep <= 1.0:
        raise SystemExit("racecav train seen-filter: --draws must be >= 1, --delay >= 0 and --keep in [0, 1]")
    try:
        suite = open_suite(args.source)
    except ValueError as e:
        raise SystemExit(f"racecav train seen-filter: {e}") from None
    if args.out.resolve() == suite.root.resolve():
        raise SystemExit("racecav train seen-filter: --out is the source suite's own folder")
    entries = suite.manifest["splits"]["train"]
    rates = pass_rates([suite.root / e["file"] for e in entries], args.draws, args.delay, args.seed,
                       progress=not args.no_progress)
    kept = [dict(e, seen_pass_rate=r) for e, r in zip(entries, rates) if r >= args.keep]
    if args.out.exists():
        shutil.rmtree(args.out)
    (args.out / "train").mkdir(parents=True)
    for e in kept:
        shutil.copy2(suite.root / e["file"], args.out / e["file"])
    manifest = {**{k: v for k, v in suite.manifest.items() if k != "splits"}, "name": args.out.name,
                "filtered_from": str(suite.root), "seen_filter": {"draws": args.draws, "delay": args.delay,
                                                                  "keep": args.keep, "seed": args.seed},
                "splits": {"train": kept, "test": []}}
    (args.out / "suite.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(f"{suite.root.name}: kept {len(kept)} of {len(entries)} train files in {args.out} "
          f"(seeing planner freed {args.delay} periods after first sight, >= {args.keep:.0%} of {args.draws} draws)")
    for fam in suite.families:
        n = sum(e["family"] == fam for e in entries)
        if n:
            mine = [r for e, r in zip(entries, rates) if e["family"] == fam]
            print(f"  {fam}: kept {sum(e['family'] == fam for e in kept)} of {n}, "
                  f"mean pass rate {sum(mine) / n:.0%}")
    return 0
