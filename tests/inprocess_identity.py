"""The in-process outcomes of the shipped policies and the two references, as JSON: a check that a
refactoring of the trial loops left behaviour unchanged (not a pytest test: it takes minutes).

    python tests/inprocess_identity.py OUT.json [--suite conflicts] [--seeds 40] [--api MODULE] [--drivers A,B]
    python tests/inprocess_identity.py OUT.json --merge PART1.json PART2.json   (drivers run apart)
    cmp OUT.json tests/data/inprocess_outcomes_3a95a65.json

For each driver: the paper-timed and conflict-timed scenarios in PyBullet, seeds 0..N-1 (each
trial's success and contact, a sha256 of every trial's ego and obstacle paths), and N fast-world
episodes of the suite's train split (selection seeds). The reference file was written at commit
3a95a65, before the trial loops moved to evaluation/inprocess.py (``--api
racecav.training.select``), on the suite of ``racecav suite generate --name conflicts --n 14
--n-train 80 --seed 0 --out DIR`` (``--suite DIR``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

POLICIES = ("racing", "default", "reversed", "avoid-paper", "avoid")


def _api(module: str):
    """The trial loops and reference drivers: evaluation/inprocess.py, or training/select.py at
    3a95a65, before they moved (``--api racecav.training.select``)."""
    import importlib

    m = importlib.import_module(module)
    print(f"trial loops of {m.__file__}", file=sys.stderr)
    return m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--suite", default="conflicts", help="suite NAME or folder (racecav suite generate --name conflicts)")
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--api", default="racecav.evaluation.inprocess", help="the module holding the trial loops")
    ap.add_argument("--drivers", help="comma-separated policy names and/or 'references' (default: the five policies and the references)")
    ap.add_argument("--merge", nargs="+", type=Path, help="write OUT.json as the union of these partial outputs")
    args = ap.parse_args(argv)
    if args.merge:
        out = {}
        for part in args.merge:
            out.update(json.loads(part.read_text()))
        args.out.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
        return 0

    import torch

    from racecav.common import registry
    from racecav.common.policy import load_policy

    torch.set_num_threads(1)
    m = _api(args.api)
    drivers = {name: load_policy(name) for name in POLICIES}
    drivers.update(m.reference_drivers())
    if args.drivers:  # "references": both non-evading references
        names = [n for k in args.drivers.split(",") for n in (m.reference_drivers() if k == "references" else [k])]
        drivers = {k: drivers[k] for k in names}
    out = {}
    for name, drv in drivers.items():
        cells = {}
        for sc in (*registry.PAPER_SCENARIOS, *registry.CONFLICT_SCENARIOS):
            r = m.eval_scenario(drv, sc, args.seeds, 0, record=args.seeds)
            paths = r.pop("paths")
            cells[sc] = {"success": [int(p["success"]) for p in paths], "contact": [int(p["contact"]) for p in paths],
                         "progress": r["progress"],
                         "paths_sha256": hashlib.sha256(json.dumps([p["xy"] for p in paths]).encode()).hexdigest()}
        cells["fast"] = m.eval_suite_fast(drv, m.policy_view_env(drv, args.suite), args.seeds)
        out[name] = cells
        print(name, {k: sum(v["success"]) for k, v in cells.items() if k != "fast"}, cells["fast"]["suite_success"],
              file=sys.stderr, flush=True)
        args.out.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")  # after each driver: a partial file
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
