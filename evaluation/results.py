"""Evaluation results: the versioned JSON schema, per-trial JSONL records and the statistics.

One evaluation run (a scenario x a controller, N seeded trials) is a :class:`RunResult`. Its
JSON Schema is generated from these models and committed as docs/results-schema.json
(``python -m racecav.evaluation.results --write-schema``; a test checks the file is current), so
the document and the code cannot drift apart. Results are validated by
:func:`validate_run` (pydantic: the same rules as the schema).

While a run is going, every finished trial is appended as one line of JSON (a
:class:`TrialRecord`: the run key + the trial) to a JSONL file, so an interrupted evaluation can
be resumed (``--resume``) and a partial one is visible as such.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

SCHEMA_ID = "racecav.eval.run"
SCHEMA_VERSION = 1
SCHEMA_PATH = Path(__file__).resolve().parents[1] / "docs" / "results-schema.json"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


class Stats(_Strict):
    """Summary of samples (milliseconds for latencies)."""

    n: int = Field(ge=0)
    median: float | None = None
    p99: float | None = None
    max: float | None = None


class Trajectory(_Strict):
    """Ground-truth poses of one trial, one row per control step (sim time)."""

    t: list[float]
    """Trial time (s) of each row."""
    ego: list[tuple[float, float, float]]
    """Ego x, y (m), yaw (rad), world frame."""
    obstacles: list[list[tuple[float, float, float]]]
    """Per obstacle car: x, y, yaw per row (same rows as ``t``)."""


class Measures(_Strict):
    """The benchmark's per-trial measures, computed when the trial ends from its recorded ground
    truth (evaluation/metrics.py holds the thresholds; docs/results.md defines them)."""

    impact_speed_mps: float | None = None
    """Contact: speed relative to what was hit (a car's velocity, a wall's none) at the last
    control step before contact; null without contact."""
    impact_band: int | None = Field(None, ge=0, le=4)
    """Euro NCAP AEB band of the impact speed, Froude-scaled to 1/10: 0 below 0.44 m/s (5 km/h full
    scale, scores 1), 1 below 1.32 (15 km/h, 0.75), 2 below 2.64 (30 km/h, 0.5), 3 below 3.51
    (40 km/h, 0.25), 4 above (0)."""
    frozen: bool = False
    """Standing (< 0.05 m/s) more than 2 s while its path was free, or the time ran out without
    contact short of its route."""
    frozen_reason: Literal["", "standing", "short"] = ""
    longest_free_standing_s: float = 0.0
    """Longest time standing with the path free (the corridor 1.5 m ahead, free for 1 s after)."""
    from_rest: bool = False
    """It started standing."""
    drive_off_s: float | None = None
    """From rest: trial time when its speed first reached 0.2 m/s; null if it never did (or it
    did not start from rest)."""
    route_completion: float = Field(0.0, ge=0, le=1)
    """progress_m / the scenario's min_progress_m, clipped to [0, 1]."""
    infraction: Literal["", "vehicle", "static", "timeout"] = ""
    driving_score: float = Field(0.0, ge=0, le=1)
    """CARLA Leaderboard: route_completion x 0.6 (vehicle) / 0.65 (static) / 0.7 (timeout)."""


class Trial(_Strict):
    """One trial."""

    index: int = Field(ge=0)
    """Position in the run (trial i uses seed = base_seed + i)."""
    seed: int
    success: bool
    """No contact during the scenario's duration and at least its min_progress_m of progress."""
    collided: bool
    contact_with: str
    """"" (no contact), "car<k>" (obstacle k), "wall", "ground" or "rollover"."""
    contact_time_s: float | None
    """Trial time of the first contact; null without contact."""
    end_time_s: float
    """Trial time when it ended (contact or the scenario's duration)."""
    progress_m: float
    """Ego progress along its initial heading (roads) or the centerline (loops)."""
    min_gap_m: float | None
    """Minimum distance between the ego's and any obstacle car's footprints (0 = touching);
    null when the scenario has no obstacle cars."""
    min_center_distance_m: float | None
    """Minimum centre-to-centre distance to any obstacle car."""
    steps: int = Field(ge=0)
    """Control steps (scans) in the trial."""
    commands: int = Field(ge=0)
    """Commands seen answering this trial's scans."""
    latency_ms: Stats
    """Scan -> command: from the scan's arrival at the router to the arrival of the command
    answering it (its scan_seq), both stamped by the router's clock (Zenoh timestamping): the
    controller's whole leg, two Zenoh hops + decode + compute + publish."""
    latency_clock: str = "router"
    """Clock of latency_ms: "router" (router timestamps), "harness" (arrival at the harness's
    client, when the router does not stamp samples), or both joined by "+"; "none" if unmeasured."""
    compute_ms: Stats
    """The controller's own compute time (DriveCommand.compute_ns)."""
    wall_s: float
    """Wall time the trial took."""
    latency_steps_ms: list[float] = []
    """Every step's scan -> command latency (ms), for run-level percentiles."""
    compute_steps_ms: list[float] = []
    """Every step's compute_ns in ms."""
    trajectory: Trajectory | None = None
    measures: Measures | None = None
    """The benchmark's measures (null in cells recorded before they existed)."""


class TrialRecord(_Strict):
    """One line of the JSONL progress file: the run it belongs to, and the trial."""

    run_key: str
    trial: Trial


class ScenarioInfo(_Strict):
    name: str
    ref: str
    """What was asked for: a shipped name or a file path."""
    digest: str
    """sha256 of the scenario file, so results of an edited file are not mixed."""
    duration_s: float


class ControllerInfo(_Strict):
    name: str
    """drl-reversed, drl-default, mpc-apf or scripted."""
    command: list[str]
    """The racecav command line that ran it."""
    service: str
    weights_sha256: str | None = None
    """sha256 of the policy weights file evaluated (DRL controllers)."""
    compute_charge_ms: float | None = None
    """Lockstep: the fixed compute time the sim charged each command (the registry's charge_ms);
    null: each command's own measured compute_ns (``--compute-charge measured``, and every cell
    recorded before the fixed charge)."""


class Summary(_Strict):
    trials: int = Field(ge=0)
    successes: int = Field(ge=0)
    success_rate: float | None
    ci95: tuple[float, float] | None
    """95 % Wilson score interval of the success rate."""
    collisions: int = Field(ge=0)
    mean_progress_m: float | None
    median_min_gap_m: float | None
    latency_ms: Stats
    """Over every step of every trial."""
    compute_ms: Stats
    measured: int = Field(0, ge=0)
    """Trials with measures (the fields below are over these; null when none)."""
    frozen: int | None = None
    timeouts: int | None = None
    """No contact, short of the route when the time ran out (frozen by definition)."""
    mean_driving_score: float | None = None
    mean_route_completion: float | None = None
    impact_bands: list[int] | None = None
    """Collisions per Euro NCAP impact band (Measures.impact_band 0-4)."""
    median_impact_speed_mps: float | None = None
    from_rest: int | None = None
    never_drove_off: int | None = None
    """From rest and never reached 0.2 m/s."""
    median_drive_off_s: float | None = None


class RunResult(_Strict):
    """An evaluation run: ``racecav eval --scenario S --controller C``."""

    schema_id: Literal["racecav.eval.run"] = SCHEMA_ID
    schema_version: Literal[1] = SCHEMA_VERSION
    created_utc: str
    git_commit: str
    machine: str
    scenario: ScenarioInfo
    controller: ControllerInfo
    mode: Literal["lockstep", "realtime"]
    base_seed: int
    trials_requested: int = Field(ge=0)
    complete: bool
    """False when fewer than trials_requested trials finished (interrupted or failed)."""
    stopped_reason: str = ""
    """Why a partial run stopped (interrupt, error text)."""
    wall_s: float
    """Wall time of the invocation that wrote this file, start-up included; a resumed run counts
    only its own part (the trials' wall_s add up to all of it)."""
    summary: Summary
    sim_counters: dict[str, int | float | str | bool | None] = {}
    """The sim service's status at the end (lockstep_republish, stale_commands, watchdog_brakes,
    overruns...): a run that needed republished scans or braked on a silent controller shows it."""
    controller_counters: dict[str, Any] = {}
    """The controller service's status info at the end (answered, stale, malformed...)."""
    trials: list[Trial]


def json_schema() -> dict:
    """The JSON Schema (draft 2020-12) of a results file."""
    schema = RunResult.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = f"https://racecav/{SCHEMA_ID}/{SCHEMA_VERSION}"
    schema["description"] = ("Results of `racecav eval` (one scenario x one controller). "
                             "Generated from racecav.evaluation.results; do not edit by hand.")
    return schema


def validate_run(data: dict | str | Path) -> RunResult:
    """Parse and validate a results file or dict.

    :raises ValueError: naming the invalid field(s).
    """
    if isinstance(data, (str, Path)):
        data = json.loads(Path(data).read_text())
    try:
        return RunResult.model_validate(data)
    except ValidationError as e:
        errs = "; ".join(f"{'.'.join(str(p) for p in x['loc'])}: {x['msg']}" for x in e.errors()[:5])
        raise ValueError(f"results do not match schema {SCHEMA_ID} v{SCHEMA_VERSION}: {errs}") from None


# ---------------------------------------------------------------------------- statistics

def wilson(successes: int, n: int, z: float = 1.959964) -> tuple[float, float] | None:
    """95 % Wilson score interval of a binomial proportion (good for small n and p near 0/1)."""
    if n <= 0:
        return None
    p = successes / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    # the interval holds p: at p = 0 or 1 the bound equals it, not p -+ 1e-16 of rounding
    return max(0.0, min(p, centre - half)), min(1.0, max(p, centre + half))


def stats(samples) -> Stats:
    a = np.asarray(list(samples), dtype=float)
    if a.size == 0:
        return Stats(n=0)
    return Stats(n=int(a.size), median=float(np.median(a)), p99=float(np.percentile(a, 99)),
                 max=float(a.max()))


def summarize(trials: list[Trial]) -> Summary:
    """Summary of finished trials (latencies pooled over every step of every trial)."""
    n = len(trials)
    ok = sum(t.success for t in trials)
    gaps = [t.min_gap_m for t in trials if t.min_gap_m is not None]
    latencies_ms = [v for t in trials for v in t.latency_steps_ms]
    computes_ms = [v for t in trials for v in t.compute_steps_ms]
    return Summary(trials=n, successes=ok, success_rate=ok / n if n else None, ci95=wilson(ok, n),
                   collisions=sum(t.collided for t in trials),
                   mean_progress_m=float(np.mean([t.progress_m for t in trials])) if n else None,
                   median_min_gap_m=float(np.median(gaps)) if gaps else None,
                   latency_ms=stats(latencies_ms), compute_ms=stats(computes_ms),
                   **measure_summary([t.measures for t in trials if t.measures is not None]))


def measure_summary(ms: list[Measures]) -> dict:
    """Summary fields over the trials' measures (empty: measured 0, the rest null)."""
    if not ms:
        return {}
    impacts = [m.impact_speed_mps for m in ms if m.impact_speed_mps is not None]
    rest = [m for m in ms if m.from_rest]
    offs = [m.drive_off_s for m in rest if m.drive_off_s is not None]
    return {"measured": len(ms), "frozen": sum(m.frozen for m in ms),
            "timeouts": sum(m.infraction == "timeout" for m in ms),
            "mean_driving_score": float(np.mean([m.driving_score for m in ms])),
            "mean_route_completion": float(np.mean([m.route_completion for m in ms])),
            "impact_bands": [sum(m.impact_band == b for m in ms) for b in range(5)],
            "median_impact_speed_mps": float(np.median(impacts)) if impacts else None,
            "from_rest": len(rest), "never_drove_off": len(rest) - len(offs),
            "median_drive_off_s": float(np.median(offs)) if offs else None}


# ---------------------------------------------------------------------------- JSONL progress

def file_digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def run_key(scenario_digest: str, controller: str, mode: str, base_seed: int, weights_digest: str | None = None) -> str:
    """What makes two runs' trials interchangeable (a resumed run must match it)."""
    ctrl = controller if weights_digest is None else f"{controller}@{weights_digest[:12]}"
    return f"{ctrl}|{mode}|seed{base_seed}|{scenario_digest[:16]}"


def read_jsonl(path: Path, key: str) -> dict[int, Trial]:
    """Finished trials of a progress file, by index.

    :raises ValueError: when a line belongs to another run or is malformed (a torn last line,
        from a kill mid-write, is ignored).
    """
    done: dict[int, Trial] = {}
    if not path.exists():
        return done
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = TrialRecord.model_validate_json(line)
        except ValidationError as e:
            if i == len(lines) - 1:
                continue  # torn last line: that trial is simply run again
            raise ValueError(f"{path}:{i + 1}: not a trial record: {e.errors()[0]['msg']}") from None
        if rec.run_key != key:
            raise ValueError(f"{path}:{i + 1}: belongs to run {rec.run_key!r}, not {key!r} "
                             "(different controller, mode, seed or scenario file); use another --jsonl "
                             "or drop --resume to start over")
        done[rec.trial.index] = rec.trial
    return done


def append_jsonl(path: Path, key: str, trial: Trial) -> None:
    with open(path, "a") as f:
        f.write(TrialRecord(run_key=key, trial=trial).model_dump_json() + "\n")
        f.flush()


if __name__ == "__main__":
    import sys

    if sys.argv[1:] == ["--write-schema"]:
        SCHEMA_PATH.write_text(json.dumps(json_schema(), indent=2) + "\n")
        print(f"wrote {SCHEMA_PATH}")
    else:
        print(json.dumps(json_schema(), indent=2))
