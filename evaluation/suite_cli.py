"""``racecav suite generate|list``: the conflict suites of family files (evaluation/suite.py) and
the roads benchmark (evaluation/benchmark.py), written to runs/suites/NAME (docs/world.md). Here,
apart from both generators, because the roads generator reuses the suite file's model."""

from __future__ import annotations

import argparse
from pathlib import Path

from racecav.common.scenario import SUITES_RUNS_DIR as RUNS_DIR, open_suite
from racecav.evaluation import benchmark
from racecav.evaluation.suite import SPLITS, SUITES_DIR, generate, load_families

def _is_benchmark(name_or_path: str) -> bool:
    """A suite file for the roads generator (``generator = "roads"``), not a family file."""
    import tomllib

    path = Path(name_or_path)
    if not path.suffix:
        path = SUITES_DIR / f"{name_or_path}.toml"
    try:
        return "generator" in tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return False  # the family loader names the problem


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="suite_cmd", required=True, metavar="ACTION")
    g = sub.add_parser("generate", help="draw, validate and write a suite's train and test splits",
                       description="draw, validate and write a suite's train and test splits",
                       epilog="example: racecav suite generate --name conflicts --n 140 --n-train 1400")
    g.add_argument("--name", default="conflicts", help="suite name (default conflicts): runs/suites/NAME")
    g.add_argument("--families", help="family file (default: common/data/suites/NAME.toml)")
    g.add_argument("--n", type=int, help="test files in all, spread over the families by weight (default 140); "
                   "a roads suite: files per family in test, ood and controls (default: the suite file's n_test)")
    g.add_argument("--n-train", type=int, help="train files in all (default 1400); a roads suite: per family")
    g.add_argument("--splits", help="the splits to (re)write, comma-separated (default all: train,test; a roads "
                   "suite: train,test,ood,controls); the others are kept")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--out", type=Path, help="output folder (default runs/suites/NAME)")
    g.add_argument("--no-progress", action="store_true")
    ls = sub.add_parser("list", help="files per family and split of a generated suite")
    ls.add_argument("suite", nargs="?", default="conflicts", help="NAME or DIR")


def run(args, cfg) -> int:
    try:
        if args.suite_cmd == "generate":
            if (args.n is not None and args.n < 1) or (args.n_train is not None and args.n_train < 1):
                print("racecav suite: --n and --n-train must be >= 1")
                return 2
            out = args.out or RUNS_DIR / args.name
            roads = _is_benchmark(args.families or args.name)
            known = benchmark.SPLITS if roads else SPLITS
            splits = tuple(s.strip() for s in (args.splits or ",".join(known)).split(",") if s.strip())
            bad = [s for s in splits if s not in known]
            if bad or not splits:
                print(f"racecav suite: --splits: unknown split(s) {bad} (choose from {', '.join(known)})")
                return 2
            if roads:
                bf = benchmark.load_benchmark(args.families or args.name)
                man = benchmark.generate(bf, out, args.seed, splits, progress=not args.no_progress,
                                         n_test=args.n, n_train=args.n_train)
            else:
                ff = load_families(args.families or args.name)
                man = generate(ff, out, args.n or 140, args.n_train or 1400, args.seed, progress=not args.no_progress,
                               splits=splits)
        else:
            s = open_suite(args.suite)
            man, out = s.manifest, s.root
    except ValueError as e:
        print(f"racecav suite: {e}")
        return 2
    for split in man["splits"]:
        fams: dict[str, int] = {}
        for e in man["splits"].get(split, []):
            fams[e["family"]] = fams.get(e["family"], 0) + 1
        red = man.get("redrawn", {}).get(split, {})
        print(f"{split}: {sum(fams.values())} files in {out / split}: "
              + ", ".join(f"{k} {v} (redrawn {red.get(k, 0)})" for k, v in fams.items()))
    return 0
