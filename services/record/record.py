"""``racecav record``: write a run to one MCAP file (raw bus samples + ROS 2 copies).

A separate process subscribed to the car's keys: the control path (scan -> controller -> command)
never waits for it. Zenoh's callback only appends the sample to a queue; the recorder's own loop
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
    p.add_argument("-o", "--output", default="run.mcap", help="output MCAP file (default: run.mcap)")
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


ROTATE = object()
"""Queue marker: switch to a new file at this point of the sample stream."""


class Recorder(Service):
    """Subscribes to key expressions and writes every sample to a run file.

    :param cfg: whole configuration (bus: car and router).
    :param output: the .mcap path.
    :param exprs: key expressions to record.
    :param duration_s: stop after this long (None: until stopped).
    :param ros: write ROS 2 copies of scan/state/cmd.
    :param nice: scheduling niceness added to this process (0: none).
    """

    def __init__(self, cfg: Config, output: str | Path, exprs: list[str], duration_s: float | None = None,
                 ros: bool = True, name: str = "record", nice: int = 10):
        super().__init__(cfg, name)
        from racecav.services.record.mcapfile import RunWriter

        self.exprs, self.duration_s, self._ros = exprs, duration_s, ros
        self.writer = RunWriter(output, self.car, ros=ros, car_params=cfg.ros2.car,
                                metadata={"config_digest": cfg.digest(), "keys": " ".join(exprs)})
        self._open_files = {os.path.realpath(output)}  # the file being written and those a rotate queued
        self._rotate_lock = threading.Lock()
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._t0 = time.monotonic()
        self.linger_s = 0.3
        if nice:
            os.nice(nice)  # below the controllers: a busy CPU serves the control path first

    def setup(self) -> None:
        for expr in self.exprs:
            self._declared.append(self.session.declare_subscriber(expr, self._on_sample))
        self.queryable("rotate", self._on_rotate)

    def _on_rotate(self, payload: bytes | None) -> dict[str, Any]:
        """racecav/<car>/<name>/rotate {"path": P}: close the file, go on in P (one file per
        trial: ``racecav eval --record``). Queued behind the samples already received, so every
        sample that arrives after the reply goes to P. P is opened here: a path that cannot be
        written (a folder, a file as a parent, a name too long) or a file still being written is
        refused with an error reply, and recording goes on in the current file."""
        try:
            data = json.loads(payload) if payload else {}
        except (ValueError, RecursionError) as e:  # not UTF-8, not JSON, nested beyond the parser
            raise ValueError(f"rotate: payload is not JSON ({e})") from None
        path = data.get("path") if isinstance(data, dict) else None
        if not isinstance(path, str) or not path or "\0" in path:
            raise ValueError('rotate: payload must be {"path": "new.mcap"}')
        real = os.path.realpath(path)
        with self._rotate_lock:
            if real in self._open_files:
                raise ValueError(f"rotate: {path} is being written")
            try:
                writer = self._new_writer(path)
            except OSError as e:
                raise ValueError(f"rotate: cannot write {path}: {e}") from None
            self._open_files.add(real)
        self._q.put((ROTATE, writer, 0))
        return {"file": path}

    def _new_writer(self, path: str):
        from racecav.services.record.mcapfile import RunWriter

        return RunWriter(path, self.car, ros=self._ros, car_params=self.cfg.ros2.car,
                         metadata={"config_digest": self._config_digest, "keys": " ".join(self.exprs)})

    def _on_sample(self, sample) -> None:
        # Zenoh's thread: no decoding, no file I/O, only a non-blocking append.
        self._q.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def _drain(self, timeout: float | None) -> None:
        try:
            item = self._q.get(timeout=timeout) if timeout else self._q.get_nowait()
        except queue.Empty:
            return
        while item is not None:
            key, payload, t = item
            if key is ROTATE:
                self._rotate(payload)
            else:
                self.received += 1
                try:
                    self.writer.write(key, payload, t)
                except Exception as e:  # one bad sample must not cost the rest of the batch
                    self.invalid += 1
                    self._record_error(f"record {key}: {type(e).__name__}: {e}")
            item = self._next()

    def _next(self):
        try:
            return self._q.get_nowait()
        except queue.Empty:
            return None

    def _rotate(self, writer) -> None:
        old, self.writer = self.writer, writer  # opened by the query: switching cannot fail
        try:
            old.close()
        finally:
            with self._rotate_lock:
                self._open_files.discard(os.path.realpath(old.path))
        self.log.info("closed %s, recording to %s", old.path, writer.path)

    def step(self) -> None:
        # Batches every 50 ms instead of waking on each sample: one wake-up per batch leaves the
        # CPU to the control path (2 cores on the car).
        self.stop_event.wait(0.05)
        self._drain(None)
        if self.duration_s is not None and time.monotonic() - self._t0 >= self.duration_s:
            self.request_stop()

    def teardown(self) -> None:
        # Asked to stop: keep listening a moment for samples still on their way (the last command
        # of a trial when `racecav eval --record` stops everything right after it).
        time.sleep(self.linger_s)

    def info(self) -> dict[str, Any]:
        return {"file": str(self.writer.path), "messages": dict(self.writer.counts),
                "bytes": self.writer.bytes, "queued": self._q.qsize()}

    def close(self) -> None:
        try:
            super().close()  # no more callbacks after this
        finally:
            self._drain(None)
            self.writer.close()
            self.log.info("wrote %s: %s", self.writer.path,
                          ", ".join(f"{k} {n}" for k, n in sorted(self.writer.counts.items())))


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
