"""``racecav record``: write a run to one MCAP file (raw bus samples + ROS 2 copies).

A separate process subscribed to the car's keys: the control path (scan -> controller -> command)
never waits for it. Each sample is logged at its own stamp (sim time in the simulator). Queries:
``rotate`` (go on in another file of the same folder; with ``hold``, cut at a stamp ``release``
names: one file per trial, exactly, for ``racecav eval --record``) and ``release``. Zenoh's callback only appends the sample to a queue; the recorder's own loop
writes the file (docs/benchmarks.md, record: the controller's latency with and without it).
The file layout is :mod:`racecav.services.record.mcapfile`.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import threading
import time
from pathlib import Path
from typing import Any

from racecav.common import keys
from racecav.common.bus import Service
from racecav.common.config import Config

EXAMPLES = """examples:
  racecav record -o run.mcap                       # everything of the car until Ctrl-C
  racecav record --keys scan cmd -o run.mcap       # only racecav/<car>/scan and /cmd
  racecav record --duration 10 -o runs/a.mcap      # stop after 10 s
  racecav replay run.mcap --lockstep               # then: feed its scans to a controller
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="run.mcap",
                   help="output MCAP file (default: run.mcap); its folder is the only one the rotate query "
                        "writes into")
    p.add_argument("--keys", nargs="+", metavar="KEY",
                   help="leaves under racecav/<car>/ (scan cmd state obstacles ...) or full key "
                        "expressions (default: racecav/<car>/**, everything of the car)")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until SIGINT/SIGTERM)")
    p.add_argument("--no-ros", action="store_true", help="raw samples only, no ROS 2 CDR copies")
    p.add_argument("--name", default="record", help="service name (several recorders need different names)")
    p.add_argument("--nice", type=int, default=10,
                   help="niceness added to the recorder (default 10: below the controllers)")
    p.epilog = EXAMPLES
    p.formatter_class = argparse.RawDescriptionHelpFormatter


ROTATE, RELEASE = object(), object()
"""Queue markers: switch to a new file (or hold the samples for it) at this point of the sample
stream; release the held samples at an episode's first stamp."""

HOLD_TIMEOUT_S = 30.0
"""A hold without its release (the harness died between the two queries) ends after this long:
everything held goes to the new file."""


def confine(folder: str, name: str) -> str:
    """The path of ``name`` inside ``folder`` (a real path), or ValueError naming the rule:
    relative names only, no '..', no symlink leading out of the folder."""
    if os.path.isabs(name):
        raise ValueError(f"rotate: {name}: absolute paths are refused (a name relative to the recording "
                         f"folder {folder})")
    if ".." in Path(name).parts:
        raise ValueError(f"rotate: {name}: '..' is refused (names stay inside the recording folder {folder})")
    path = os.path.join(folder, name)
    real_parent = os.path.realpath(os.path.dirname(path))
    if os.path.commonpath([real_parent, folder]) != folder:
        raise ValueError(f"rotate: {name}: leads out of the recording folder {folder} through a symlink")
    if os.path.islink(path):
        raise ValueError(f"rotate: {name}: is a symlink (refused: it may lead out of the recording folder)")
    return path


class Recorder(Service):
    """Subscribes to key expressions and writes every sample to a run file.

    Each sample is logged at its own stamp (``stamp_ns``; a sample without one, e.g. the
    e-stop, at the latest stamp seen before it): sim time in the simulator, so a lockstep trial
    plays back at its own speed.

    :param cfg: whole configuration (bus: car and router).
    :param output: the .mcap path; its folder is the only one ``rotate`` writes into.
    :param exprs: key expressions to record.
    :param duration_s: stop after this long (None: until stopped).
    :param ros: write ROS 2 copies of scan/state/cmd and the frame tree.
    :param nice: scheduling niceness added to this process (0: none).
    """

    def __init__(self, cfg: Config, output: str | Path, exprs: list[str], duration_s: float | None = None,
                 ros: bool = True, name: str = "record", nice: int = 10):
        super().__init__(cfg, name)
        from racecav.services.record.mcapfile import RunWriter

        self.exprs, self.duration_s, self._ros = exprs, duration_s, ros
        self.writer = RunWriter(output, self.car, ros=ros, car_params=cfg.ros2.car,
                                metadata={"config_digest": cfg.digest(), "keys": " ".join(exprs)})
        self.folder = os.path.realpath(os.path.dirname(os.path.abspath(output)))
        self._open_files = {os.path.realpath(output)}  # the file being written and those a rotate queued
        self._rotate_lock = threading.Lock()
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._t0 = time.monotonic()
        self.linger_s = 0.3
        self.old_linger_s = 2.0
        """After a release, samples stamped before the boundary (in flight at the reset) still go
        to the old file for this long (wall); then it is closed."""
        self._last_stamp = 0
        self._next = None  # the file a hold switches to
        self._held: list[tuple[str, bytes, int]] = []
        self._hold_since: float | None = None
        self._old = None  # (writer, boundary stamp, close at) after a release
        self._closed_boundary: int | None = None
        self.late = 0
        """Samples stamped before a release's boundary that came after the old file was closed."""
        if nice:
            os.nice(nice)  # below the controllers: a busy CPU serves the control path first

    def setup(self) -> None:
        for expr in self.exprs:
            self._declared.append(self.session.declare_subscriber(expr, self._on_sample))
        self.queryable("rotate", self._on_rotate)
        self.queryable("release", self._on_release)

    def _on_rotate(self, payload: bytes | None) -> dict[str, Any]:
        """racecav/<car>/<name>/rotate {"path": P, "hold": bool}: go on in P, a name relative to
        the recording folder (the folder of ``-o``; absolute paths, '..' and symlinks leading out
        are refused, and P is opened without following a symlink). Queued behind the samples
        already received. Without hold, every sample that arrives after the reply goes to P. With
        hold (``racecav eval --record``, before a reset), samples are held until ``release``
        names the new episode's first stamp: those stamped before it go to the old file, the
        rest to P, so a trial's file holds exactly its samples. P is opened here: a path that
        cannot be written, or a file still being written, is refused with an error reply and
        recording goes on in the current file."""
        from racecav.services.record.mcapfile import RunWriter

        try:
            data = json.loads(payload) if payload else {}
        except (ValueError, RecursionError) as e:  # not UTF-8, not JSON, nested beyond the parser
            raise ValueError(f"rotate: payload is not JSON ({e})") from None
        path = data.get("path") if isinstance(data, dict) else None
        hold = data.get("hold", False) if isinstance(data, dict) else False
        if not isinstance(path, str) or not path or "\0" in path or not isinstance(hold, bool):
            raise ValueError('rotate: payload must be {"path": "new.mcap"} (and optionally "hold": true)')
        full = confine(self.folder, path)
        real = os.path.realpath(full)
        with self._rotate_lock:
            if real in self._open_files:
                raise ValueError(f"rotate: {path} is being written")
            try:
                writer = RunWriter(full, self.car, ros=self._ros, car_params=self.cfg.ros2.car,
                                   metadata={"config_digest": self._config_digest, "keys": " ".join(self.exprs)},
                                   follow_symlinks=False)
            except OSError as e:
                raise ValueError(f"rotate: cannot write {path}: {e.strerror or e}") from None
            self._open_files.add(real)
        self._q.put((ROTATE, writer, hold))
        return {"file": full}

    def _on_release(self, payload: bytes | None) -> dict[str, Any]:
        """racecav/<car>/<name>/release {"stamp_ns": S}: end a hold at S, the first stamp of the
        new episode (the sim's reset reply carries it)."""
        try:
            data = json.loads(payload) if payload else None
        except (ValueError, RecursionError) as e:
            raise ValueError(f"release: payload is not JSON ({e})") from None
        stamp = data.get("stamp_ns") if isinstance(data, dict) else None
        if type(stamp) is not int or not 0 <= stamp < 2**63:
            raise ValueError('release: payload must be {"stamp_ns": S}, 0 <= S < 2^63')
        self._q.put((RELEASE, stamp, 0))
        return {"stamp_ns": stamp}

    def _on_sample(self, sample) -> None:
        # Zenoh's thread: no decoding, no file I/O, only a non-blocking append.
        self._q.put((str(sample.key_expr), sample.payload.to_bytes(), 0))

    def _drain(self, timeout: float | None) -> None:
        from racecav.services.record.mcapfile import stamp_of

        try:
            item = self._q.get(timeout=timeout) if timeout else self._q.get_nowait()
        except queue.Empty:
            return
        while item is not None:
            key, payload, arg = item
            if key is ROTATE:
                self._rotate(payload, arg)
            elif key is RELEASE:
                self._release(payload)
            else:
                self.received += 1
                stamp = stamp_of(payload)
                self._last_stamp = stamp = self._last_stamp if stamp is None else stamp
                if self._next is not None:
                    self._held.append((key, payload, stamp))
                else:
                    self._write(key, payload, stamp)
            item = self._next_item()

    def _next_item(self):
        try:
            return self._q.get_nowait()
        except queue.Empty:
            return None

    def _write(self, key: str, payload: bytes, stamp: int) -> None:
        writer = self.writer
        if self._old is not None and stamp < self._old[1]:
            writer = self._old[0]  # stamped before the new episode: the old trial's
        elif self._old is None and self._boundary_passed(stamp):
            self.late += 1
        try:
            writer.write(key, payload, stamp)
        except Exception as e:  # one bad sample must not cost the rest of the batch
            self.invalid += 1
            self._record_error(f"record {key}: {type(e).__name__}: {e}")

    def _boundary_passed(self, stamp: int) -> bool:
        return self._closed_boundary is not None and stamp < self._closed_boundary

    def _close_writer(self, w) -> None:
        try:
            w.close()
        finally:
            with self._rotate_lock:
                self._open_files.discard(os.path.realpath(w.path))
        self.log.info("closed %s (%d messages)", w.path, w.messages)

    def _close_old(self) -> None:
        if self._old is not None:
            w, boundary, _ = self._old
            self._old, self._closed_boundary = None, boundary
            self._close_writer(w)

    def _rotate(self, writer, hold: bool) -> None:
        if self._next is not None:  # a second hold before the first's release: end the first
            self._release(None)
        if hold:
            self._next, self._hold_since = writer, time.monotonic()
            return
        self._close_old()
        old, self.writer = self.writer, writer  # opened by the query: switching cannot fail
        self._close_writer(old)
        self.log.info("recording to %s", writer.path)

    def _release(self, boundary: int | None) -> None:
        """End a hold: the held samples go out by their stamps (None: all to the new file)."""
        if self._next is None:
            return  # a release without a hold (repeated, or the hold timed out): nothing to do
        self._close_old()
        if boundary is None:
            self._close_writer(self.writer)
        else:
            self._old = (self.writer, boundary, time.monotonic() + self.old_linger_s)
        self.writer, self._next, self._hold_since = self._next, None, None
        held, self._held = self._held, []
        for key, payload, stamp in held:
            self._write(key, payload, stamp)
        self.log.info("recording to %s from stamp %s", self.writer.path, boundary)

    def step(self) -> None:
        # Batches every 50 ms instead of waking on each sample: one wake-up per batch leaves the
        # CPU to the control path (2 cores on the car).
        self.stop_event.wait(0.05)
        self._drain(None)
        now = time.monotonic()
        if self._old is not None and now >= self._old[2]:
            self._close_old()
        if self._hold_since is not None and now - self._hold_since > HOLD_TIMEOUT_S:
            self._record_error(f"rotate: no release within {HOLD_TIMEOUT_S:.0f} s of a hold")
            self._release(None)
        if self.duration_s is not None and now - self._t0 >= self.duration_s:
            self.request_stop()

    def teardown(self) -> None:
        # Asked to stop: keep listening a moment for samples still on their way (the last command
        # of a trial when `racecav eval --record` stops everything right after it).
        time.sleep(self.linger_s)

    def info(self) -> dict[str, Any]:
        return {"file": str(self.writer.path), "messages": dict(self.writer.counts),
                "bytes": self.writer.bytes, "queued": self._q.qsize(), "held": len(self._held),
                "late": self.late}

    def close(self) -> None:
        try:
            super().close()  # no more callbacks after this
        finally:
            self._drain(None)
            if self._next is not None:
                self._release(None)
            self._close_old()
            self.writer.close()
            self.log.info("wrote %s: %s", self.writer.path,
                          ", ".join(f"{k} {n}" for k, n in sorted(self.writer.counts.items())) or "nothing (removed)")


def key_exprs(car: str, given: list[str] | None) -> list[str]:
    """Key expressions from --keys: leaves go under racecav/<car>/, anything with a '/' is taken
    as it is."""
    if not given:
        return [f"{keys.PREFIX}/{car}/**"]
    return [k if "/" in k else keys.topic(car, k) for k in given]


def run(args: argparse.Namespace, cfg: Config) -> int:
    try:
        rec = Recorder(cfg, args.output, key_exprs(cfg.bus.car, args.keys), args.duration,
                       ros=not args.no_ros, name=args.name, nice=args.nice)
    except (ImportError, OSError, ValueError) as e:
        print(f"racecav record: {e}")
        return 2
    return rec.run()
