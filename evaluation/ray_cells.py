"""``racecav eval --table|--suite ... --ray [ADDRESS]``: the cells on a Ray cluster.

Each Ray task is one cell: a (table row, scenario) or a chunk of a suite's files of about as many
trials. It requests CELL_CPUS CPUs (a router, a sim and a controller keep about two cores busy;
Ray's resources are logical and do not count a task's own children), runs a Harness on the node
Ray picks (its own router on a free port: its own bus) in a temporary folder, and returns its
records (RunResult, per-trial JSONL) to the driver. The driver writes them where a local run would
(OUT/table/*.jsonl, the cell store), so ``--resume`` and the document work as they do without
``--ray``. No shared file system: a suite's scenario files, the ``--config`` file and the
RACECAV_* settings travel with the task, and the driver checks that each returned cell has the run
key it expects (the same scenario file, controller, weights, mode and seed): a node with other
weights installed is an error, not a silently different row.

Processes: every process a cell starts carries ``RACECAV_CELL=<tag>`` in its environment
(common/procs.py). The Harness stops them when the cell ends or raises; each process also stops
itself once its parent is gone (procs.exit_with_parent), which covers a worker killed outright,
where Ray kills only direct children and only on a clean exit; and the next attempt of the cell,
and the end of every attempt, reap what still carries the tag on that node.

Retries: a task whose worker or node dies is run again by Ray, up to ``--ray-retries`` times
(its cells start over from what the driver had when it submitted them). A cell that fails inside
(a service that exits, a trial that hangs) comes back partial: the command exits 1 and ``--resume``
continues it, as without ``--ray``.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import sys
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

CELL_CPUS = 2.0
"""CPUs a cell requests: its sim and its controller each keep about one core busy."""
RETRIES = 3
"""Times Ray reruns a cell whose worker died (Ray's own default for tasks)."""


@dataclass
class Item:
    """One cell's trials (the table's RowCell, or one suite file)."""

    group: str
    """Its store group: "scenarios" or "suite-NAME"."""
    cell: str
    """Its name in the store: the scenario's name or the suite file's name."""
    ref: str
    """The scenario as the driver names it: a shipped scenario's name or a file's absolute path."""
    text: str | None
    """A scenario file's contents (None: a shipped scenario, installed on every node)."""
    trials: int
    seed: int
    keep_trajectory: bool
    key: str
    """The run key the driver expects (trials.cell_key)."""
    done: str = ""
    """JSONL lines already run (``--resume``)."""


@dataclass
class Task:
    """What one Ray task runs: a controller (with or without the supervisor) over some items."""

    tag: str
    controller: str
    safety: bool
    mode: str
    rtf: float
    items: list[Item]
    compute_charge: str = "fixed"
    """What the lockstep sim charges each command (harness.COMPUTE_CHARGES)."""
    config: str | None = None
    """The ``--config`` file's text."""
    env: dict[str, str] = field(default_factory=dict)
    """The driver's RACECAV_* settings (a remote node has none of them)."""
    perturb: dict[str, float] | None = None
    """The sim's perturbation (PerturbConfig.active(); the robust section's cells): the controller
    then runs as harness.perturbed names it, under the run key the driver expects; None: the
    configuration's sim.perturb, as without --ray."""


def run_task(task: Task) -> dict:
    """On a worker: the task's items through one Harness. Returns ``items``, one dict per item run:
    ``result`` (the RunResult as JSON), ``jsonl`` (its per-trial lines) and ``error`` ("" when it
    finished); and the cell's timing: ``node``, ``start_s`` (its services starting), ``wall_s``."""
    import platform

    from racecav.common import procs
    from racecav.common.config import PerturbConfig, load_config
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.evaluation.harness import CONTROLLERS, Harness, HarnessError, perturbed
    from racecav.evaluation.trials import NoBar, run_trials

    wall0 = time.monotonic()
    procs.reap(task.tag)  # what an earlier attempt of this cell left here (its worker was killed)
    out: list[dict] = []
    start_s = None
    with tempfile.TemporaryDirectory(prefix="racecav-cell-") as tmp_, _environ(task.env):
        tmp = Path(tmp_)
        os.environ[procs.CELL_ENV] = task.tag
        if task.config is not None:
            (tmp / "config.toml").write_text(task.config)
            os.environ["RACECAV_CONFIG"] = str(tmp / "config.toml")
        refs = []
        for k, it in enumerate(task.items):
            if it.text is None:
                refs.append((it.ref, SCENARIOS_DIR / f"{it.ref}.toml"))
            else:  # the driver's file, under its own name (the sim names a scenario by it)
                (tmp / str(k)).mkdir()
                path = tmp / str(k) / Path(it.ref).name
                path.write_text(it.text)
                refs.append((str(path), path))
        try:
            cfg = load_config()
            p = None if task.perturb is None else PerturbConfig.model_validate(task.perturb)
            ctrl = CONTROLLERS[task.controller] if p is None else perturbed(CONTROLLERS[task.controller], p)
            with Harness(cfg, ctrl, task.mode, refs[0][0], tmp / "logs", task.rtf,
                         safety=task.safety, compute_charge=task.compute_charge, perturb=p) as h:
                start_s = time.monotonic() - wall0
                for k, (it, (ref, path)) in enumerate(zip(task.items, refs)):
                    jsonl = tmp / f"{k}.jsonl"
                    jsonl.write_text(it.done)
                    res, error = run_trials(h, ref, path, it.trials, it.seed, jsonl, True, bar=NoBar(),
                                            keep_trajectory=it.keep_trajectory)
                    out.append({"result": res.model_dump_json(), "jsonl": jsonl.read_text(),
                                "error": "" if error is None else f"{type(error).__name__}: {error}"})
                    if error is not None:
                        break
        except HarnessError as e:  # the services did not start: no item ran
            out.append({"result": None, "jsonl": "", "error": f"HarnessError: {e}"})
        finally:
            os.environ.pop(procs.CELL_ENV, None)
            procs.reap(task.tag)  # none after a clean exit of the Harness; a grandchild's otherwise
    return {"items": out, "node": platform.node(), "start_s": start_s, "wall_s": time.monotonic() - wall0}


@contextlib.contextmanager
def _environ(env: dict[str, str]):
    """The driver's settings for the duration of a task (a worker runs many tasks)."""
    keys = [*env, "RACECAV_CONFIG"]
    old = {k: os.environ.get(k) for k in keys}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# ------------------------------------------------------------------------------------ driver
def _task_base(args, name: str, on: bool) -> dict:
    from racecav.common import procs

    env = {k: v for k, v in os.environ.items()
           if k.startswith("RACECAV_") and k not in ("RACECAV_CONFIG", procs.PARENT_ENV, procs.CELL_ENV)}
    cfg = os.environ.get("RACECAV_CONFIG") or getattr(args, "config", None)
    return dict(controller=name, safety=on, mode=args.mode, rtf=args.real_time_factor,
                compute_charge=getattr(args, "compute_charge", "fixed"),
                config=Path(cfg).read_text() if cfg else None, env=env)


def _item(group: str, cell: str, ref: str, path: Path, shipped: bool, trials: int, seed: int, keep: bool,
          ctrl, on: bool, mode: str, jsonl: Path, resume: bool) -> Item:
    from racecav.evaluation import results as R
    from racecav.evaluation.trials import cell_key

    key = cell_key(ctrl, on, mode, path, seed)
    done = ""
    if resume and jsonl.is_file():
        R.read_jsonl(jsonl, key)  # a JSONL of another run is refused here, naming it (ValueError)
        done = jsonl.read_text()
    return Item(group, cell, ref, None if shipped else path.read_text(), trials, seed, keep, key, done)


def _group(section: str, suite_name: str) -> str:
    """A suite-like section's store group (table._row_cells): suite-NAME, or suite-NAME-SPLIT for
    the generalization section's splits (section roads/SPLIT)."""
    return f"suite-{suite_name}" + (f"-{section.split('/', 1)[1]}" if section.startswith("roads/") else "")


def table_tasks(args, runs, cells: dict, seeds: dict, suites: dict, robust_rows: list = ()) -> list[tuple[Task, list]]:
    """(Task, the RowCells it fills) for every cell of the table the store does not hold: one task
    per scenario cell, a suite's files in chunks of about ``--trials`` trials; and so for the robust
    section's rows (``robust_rows``: robust.Row; each task carries its row's perturbation)."""
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.evaluation.harness import CONTROLLERS, perturbed

    run_id = uuid.uuid4().hex[:8]
    files = {(sec, c.path.name): c.path.resolve() for sec, (_, cs) in suites.items() for c in cs}
    trials = args.trials if args.trials is not None else 100
    tasks = []
    for name, on in runs:
        ctrl = CONTROLLERS[name]
        todo = [c for c in cells[(name, on)] if c.stored is None]
        scen = [c for c in todo if c.section not in suites]
        chunks = [[c] for c in scen]
        for sec in suites:
            sec_cells = [c for c in todo if c.section == sec]
            n = max(1, trials // max(1, args.trials_per_scenario))
            chunks += [sec_cells[i:i + n] for i in range(0, len(sec_cells), n)]
        for chunk in chunks:
            items = []
            for c in chunk:
                if c.section in suites:
                    path = files[(c.section, c.cell)]
                    items.append(_item(_group(c.section, suites[c.section][0]), c.cell, str(path), path, False, c.trials,
                                       args.seed or 0, False, ctrl, on, args.mode, c.jsonl, args.resume))
                else:
                    items.append(_item("scenarios", c.cell, c.cell, SCENARIOS_DIR / f"{c.cell}.toml", True,
                                       c.trials, seeds[c.cell], True, ctrl, on, args.mode, c.jsonl, args.resume))
            tag = f"{run_id}-{len(tasks)}"
            tasks.append((Task(tag=tag, items=items, **_task_base(args, name, on)), chunk))
    for row in robust_rows:  # robust.Cell: its own group, store name, reference and seed
        ctrl = perturbed(CONTROLLERS[row.name], row.perturb)
        scen = [c for c in row.todo if c.shipped]
        files = [c for c in row.todo if not c.shipped]
        n = max(1, trials // max(1, max((c.trials for c in files), default=1)))
        for chunk in [[c] for c in scen] + [files[i:i + n] for i in range(0, len(files), n)]:
            items = [_item(c.group, c.cell, c.ref, c.path, c.shipped, c.trials, c.seed, False, ctrl, False, args.mode,
                           c.jsonl, args.resume) for c in chunk]
            tasks.append((Task(tag=f"{run_id}-{len(tasks)}", items=items, perturb=row.perturb.active(),
                               **_task_base(args, row.name, False)), chunk))
    return tasks


def run_tasks(args, tasks: list[tuple[Task, list]], write, total: int, initial: int, log: Path | None = None) -> int:
    """Submit ``tasks`` (Task, what ``write`` needs) to Ray and hand each finished one's records to
    ``write(task, targets, records)``, which returns an error text or "". Returns 0, or 1 after
    naming the cells that failed, 2 if Ray is missing or cannot be reached. ``log``: a CSV of
    every finished cell's node and times."""
    from tqdm import tqdm

    from racecav.common import cluster

    if not tasks:  # every cell is stored already
        return 0
    try:
        ray = cluster.init(args.ray)
    except ImportError:
        print("racecav eval --ray: ray is not installed (pip install 'racecav[ray]')", file=sys.stderr)
        return 2
    except ConnectionError as e:
        print(f"racecav eval --ray: {e}", file=sys.stderr)
        return 2
    remote = ray.remote(num_cpus=getattr(args, "ray_cpus", CELL_CPUS),
                        max_retries=getattr(args, "ray_retries", RETRIES))(run_task)
    where = args.ray or "a local Ray"
    print(f"racecav eval --ray: {len(tasks)} cells on {where} "
          f"({ray.cluster_resources().get('CPU', 0):.0f} CPUs, {getattr(args, 'ray_cpus', CELL_CPUS):g} per cell)",
          flush=True)
    pending = {remote.remote(t): (t, targets) for t, targets in tasks}
    failed: list[str] = []
    timing: list[list] = []  # per cell: tag, row, cells, trials, node, start_s, wall_s
    bar = None if args.no_progress else tqdm(total=total, initial=initial, unit="trial", desc="cells (ray)",
                                             dynamic_ncols=True)
    wall0 = time.monotonic()
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=5.0)
            for ref in ready:
                task, targets = pending.pop(ref)
                try:
                    got = ray.get(ref)
                    why = write(task, targets, got["items"])
                    timing.append([task.tag, task.controller + ("+safety" if task.safety else ""),
                                   " ".join(i.cell for i in task.items), sum(i.trials for i in task.items),
                                   got["node"], "" if got["start_s"] is None else f"{got['start_s']:.2f}",
                                   f"{got['wall_s']:.2f}"])
                except (ray.exceptions.RayError, ValueError) as e:  # retries used up; a cell of another run
                    why = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
                if why:
                    failed.append(f"{task.controller}{'+safety' if task.safety else ''} "
                                  f"{', '.join(i.cell for i in task.items[:3])}: {why}")
                if bar is not None:
                    bar.update(sum(i.trials for i in task.items))
    except BaseException as e:  # interrupted: cancel the rest (their workers stop their services)
        for ref in pending:
            ray.cancel(ref, force=False)
        print(f"PARTIAL table: {type(e).__name__}: {e}; continue with the same command and --resume", file=sys.stderr)
        return 130
    finally:
        if bar is not None:
            bar.close()
    if log is not None:  # what racecav bench ray reads: the cells' own times
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("w", newline="") as f:
            csv.writer(f).writerows([["tag", "row", "cells", "trials", "node", "start_s", "wall_s"], *timing])
    print(f"racecav eval --ray: {len(tasks)} cells in {time.monotonic() - wall0:.1f} s wall"
          + (f" (per cell: {log})" if log is not None else ""), flush=True)
    for f in failed:
        print(f"racecav eval --ray: cell {f}; continue with the same command and --resume", file=sys.stderr)
    return 1 if failed else 0


def records(task: Task, recs: list[dict]):
    """(Item, RunResult, jsonl text) of a task's records, the RunResult named by the driver's
    scenario reference; raises ValueError when a cell came back under another run key."""
    from racecav.evaluation import results as R
    from racecav.evaluation.store import stored_key

    for it, rec in zip(task.items, recs):
        if rec.get("result") is None:
            continue
        res = R.validate_run(json.loads(rec["result"]))
        if stored_key(res) != it.key:
            raise ValueError(f"{it.cell} came back as run {stored_key(res)}, not {it.key}: install the same "
                             "racecav (and weights) on every node")
        res = res.model_copy(update={"scenario": res.scenario.model_copy(update={"ref": it.ref})})
        yield it, res, rec["jsonl"]


def run_table(args, runs, cells: dict, seeds: dict, suites: dict, store, total: int, initial: int,
              robust_rows: list = ()) -> int:
    """``racecav eval --table --ray``: every cell the store lacks (the robust section's rows too), as
    a Ray task; their records go to the cells' JSONL and the store. The table then writes its
    document from them (table.py); ``initial``: the trials it already has."""
    try:
        tasks = table_tasks(args, runs, cells, seeds, suites, robust_rows)
    except ValueError as e:
        print(f"racecav eval --table --ray: {e}", file=sys.stderr)
        return 2

    def write(task: Task, targets: list, recs: list[dict]) -> str:
        row = task.controller + ("+safety" if task.safety else "")
        by_cell = {c.cell: c for c in targets}
        for it, res, jsonl in records(task, recs):
            path = by_cell[it.cell].jsonl
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(jsonl)
            store.put(row, it.group, it.cell, res)  # complete cells only
        return next((r["error"] for r in recs if r["error"]), "") or \
            ("" if len(recs) == len(task.items) else "not every cell ran")

    return run_tasks(args, tasks, write, total, initial, args.out_dir / "table" / "logs" / "ray-cells.csv")


def run_suite(args, cells: list, out: Path, perturb=None) -> tuple[dict, str]:
    """``racecav eval --suite S --controller C --ray``: the split's files in chunks of about
    ``--trials`` (default 100) trials, each a Ray task (``perturb``: the sim's, ``--perturb``).
    Returns ({file: RunResult}, error text)."""
    from racecav.evaluation.harness import CONTROLLERS, perturbed

    ctrl = perturbed(CONTROLLERS[args.controller], perturb)
    k, seed = args.trials_per_scenario, args.seed if args.seed is not None else 0
    n = max(1, (args.trials or 100) // k)
    run_id, tasks, results = uuid.uuid4().hex[:8], [], {}
    try:
        for i in range(0, len(cells), n):
            items = [_item("suite", c.path.name, str(c.path.resolve()), c.path.resolve(), False, k, seed, False, ctrl,
                           False, args.mode, out / f"{c.path.stem}.jsonl", args.resume) for c in cells[i:i + n]]
            tasks.append((Task(tag=f"{run_id}-{len(tasks)}", items=items, **_task_base(args, args.controller, False),
                               perturb=None if perturb is None else perturb.active()), None))
    except ValueError as e:
        return results, str(e)

    def write(task: Task, _targets, recs: list[dict]) -> str:
        for it, res, jsonl in records(task, recs):
            out.mkdir(parents=True, exist_ok=True)
            (out / f"{Path(it.cell).stem}.jsonl").write_text(jsonl)
            results[it.cell] = res
        return next((r["error"] for r in recs if r["error"]), "") or \
            ("" if len(recs) == len(task.items) else "not every file ran")

    rc = run_tasks(args, tasks, write, len(cells) * k, 0, out / "logs" / "ray-cells.csv")
    return results, "" if rc == 0 else f"Ray cells failed (exit {rc})"
