"""The committed store of ``racecav eval --table``'s finished cells: docs/results-data/.

A full table is about 360 CPU-minutes of trials (docs/results.md's header), more than one working
session, and its per-trial JSONL (trajectories, per-step latencies: several kB a trial) is too big
to commit. The store keeps what the document needs of every complete cell, compactly, so that a
fresh clone regenerates docs/results.md from it (``racecav eval --table ... --resume`` runs only
the cells it lacks; ``--from-store`` runs none) and a table can be computed over several sessions,
one committed batch of rows at a time.

A cell is stored as its RunResult with the summary computed from the full data (latency
percentiles pooled over every step) and the per-trial outcomes (seed, success, contact, gap,
progress, wall time, per-trial latency stats), without the per-step latency arrays and without
trajectories except trial 0's (the document's Figure 4). Cells are reused only when complete
and under the same run key (scenario file digest, controller, policy weights digest, mode, seed)
and trial count as asked. The key holds no digest of the code: a cell keeps the commit it was
measured at, and code_drift names the files of the trial code (MEASURED_CODE) changed since, which
the table prints and writes in the document's header (rerun those cells without --resume if the
change matters: a changed docstring does not, a changed contact test does).

One gzip file per (table row, group): ROW.scenarios.json.gz (the paper's and the conflict-timed
scenarios) and ROW.suite-NAME.json.gz (one cell per suite file).
"""

from __future__ import annotations

import gzip
import json
import os
import subprocess
from pathlib import Path

MEASURED_CODE = ("sim", "services", "common", "evaluation/harness.py", "evaluation/trials.py",
                 "evaluation/suite_eval.py", "evaluation/metrics.py", "evaluation/results.py")
"""What decides a cell's outcome (simulator, services, cars and worlds, the trial runner and its
summary), as paths of the checkout; the table's writing (table.py, plots.py, this module) is not."""


def compact(res):
    """The RunResult as stored: no per-step arrays, trial 0's trajectory only."""
    trials = [t.model_copy(update={"latency_steps_ms": [], "compute_steps_ms": [],
                                   "trajectory": t.trajectory if t.index == 0 else None})
              for t in res.trials]
    return res.model_copy(update={"trials": trials})


class CellStore:
    """Complete cells by (row, group, cell name); see the module docstring."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self._files: dict[Path, tuple[tuple | None, dict]] = {}  # path -> (its stamp when read, its cells)

    def _path(self, row: str, group: str) -> Path:
        return self.root / f"{row}.{group}.json.gz"

    @staticmethod
    def _stamp(path: Path) -> tuple | None:
        try:
            st = path.stat()
        except FileNotFoundError:
            return None
        return st.st_mtime_ns, st.st_size

    def _load(self, path: Path) -> dict:
        # read again when the file changed: --jobs children write the rows their parent then reads
        stamp = self._stamp(path)
        if path not in self._files or self._files[path][0] != stamp:
            cells = {}
            if stamp is not None:
                try:
                    with gzip.open(path, "rt") as f:
                        cells = json.load(f)
                except (OSError, ValueError) as e:
                    raise ValueError(f"{path}: not a results store file ({e}); delete it to recompute its cells") \
                        from None
            self._files[path] = (stamp, cells)
        return self._files[path][1]

    def get(self, row: str, group: str, cell: str, key: str, trials: int):
        """The stored RunResult of a cell, or None if absent, partial or of another run key."""
        from racecav.evaluation import results as R

        data = self._load(self._path(row, group)).get(cell)
        if data is None:
            return None
        res = R.validate_run(data)
        if not res.complete or res.trials_requested != trials or stored_key(res) != key:
            return None
        return res

    def put(self, row: str, group: str, cell: str, res) -> None:
        """Store a complete cell (a partial one is left to the JSONL under --out-dir)."""
        if not res.complete:
            return
        path = self._path(row, group)
        cells = self._load(path)
        cells[cell] = compact(res).model_dump(mode="json")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        text = json.dumps({k: cells[k] for k in sorted(cells)}, separators=(",", ":"))
        with open(tmp, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as f:  # same bytes for same cells
            f.write(text.encode())
        os.replace(tmp, path)
        self._files[path] = (self._stamp(path), cells)


def stored_key(res) -> str:
    """The run key (results.run_key) a stored cell was computed under."""
    from racecav.evaluation import results as R

    return R.run_key(res.scenario.digest, res.controller.name, res.mode, res.base_seed, res.controller.weights_sha256)


def code_drift(commits, root: Path | None = None) -> dict[str, list[str] | None]:
    """Per commit as cells record it (``git describe --always --dirty``), the MEASURED_CODE files
    that differ between it and this checkout's working tree; None when git cannot tell (no git, a
    commit this clone lacks, "unknown"). A "-dirty" commit had uncommitted changes of its own."""
    root = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    out: dict[str, list[str] | None] = {}
    for c in commits:
        try:
            r = subprocess.run(["git", "diff", "--name-only", c.removesuffix("-dirty"), "--", *MEASURED_CODE],
                               cwd=root, capture_output=True, text=True, timeout=30)
            out[c] = r.stdout.split() if r.returncode == 0 else None
        except (OSError, subprocess.SubprocessError):
            out[c] = None
    return out


def drift_text(commits: dict[str, int], drift: dict[str, list[str] | None]) -> str:
    """One sentence on the code the reused cells were measured with (``commits``: cells per
    commit), for the document's header and the console; "" when no cell was reused."""
    if not commits:
        return ""
    at = ", ".join(f"{c} ({n})" for c, n in sorted(commits.items()))
    changed = {c: f for c, f in drift.items() if f}
    unknown = [c for c, f in drift.items() if f is None]
    text = f"The {sum(commits.values())} stored cells reused here were measured at commit {at}. "
    dirty = " (a -dirty commit's own uncommitted changes are not known)" if any(c.endswith("-dirty") for c in commits) else ""
    if not changed and not unknown:
        return text + f"The trial code ({', '.join(MEASURED_CODE)}) has not changed since{dirty}."
    parts = [f"since {c}: {', '.join(f[:6])}{' ...' if len(f) > 6 else ''}" for c, f in sorted(changed.items())]
    if unknown:
        parts.append(f"git cannot compare {', '.join(sorted(unknown))}")
    return text + ("The trial code changed " + "; ".join(parts) + dirty
                   + ". Rerun the cells without --resume if the change can move a result.")
