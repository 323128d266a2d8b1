"""The e-stop latch that survives restarts.

An e-stop must hold until someone clears it, whatever happens to the processes in between. Two
copies of the latch are kept, and the actuator (and the simulator) start latched if either says
so:

- a file, ``<state_dir>/estop-<car>.json``, written (atomically, fsynced) by the actuator when the
  latch changes: a killed and restarted actuator starts latched;
- the router's memory: ``racecav router`` listens to racecav/<car>/estop and answers the query
  racecav/<car>/router/estop, so an e-stop published while the actuator was down (nobody else
  listening) still takes effect when it starts.

Only the exact payload ``b"clear"`` clears (both copies); any other payload latches. The two
copies are combined with OR: a clear that only one of them saw leaves the car stopped until the
next clear (a conservative choice: a spurious stop costs a clear, a lost stop costs a crash).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

CLEAR = b"clear"


def is_clear(payload: bytes) -> bool:
    """True only for exactly b"clear" (not "CLEAR", not " clear\\n")."""
    return bytes(payload) == CLEAR


def default_state_dir() -> Path:
    """systemd's $STATE_DIRECTORY (StateDirectory=racecav), else ~/.local/state/racecav."""
    env = os.environ.get("STATE_DIRECTORY")
    if env:
        return Path(env.split(":")[0])
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "racecav"


class LatchFile:
    """The on-disk copy of the latch.

    :param state_dir: directory of the file (None: :func:`default_state_dir`).
    :param car: car name (one file per car).
    """

    def __init__(self, state_dir: Path | None, car: str):
        self.path = Path(state_dir or default_state_dir()) / f"estop-{car}.json"
        self.error = ""
        """Why the last write failed ("" if it worked): reported in the status."""

    def load(self) -> dict | None:
        """The latch record if the file says latched, else None. An unreadable or corrupt file
        counts as latched (it was written by a latch)."""
        try:
            data = json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as e:
            return {"latched": True, "detail": f"unreadable latch file: {e}"}
        if isinstance(data, dict) and data.get("latched") is False:
            return None
        return data if isinstance(data, dict) else {"latched": True, "detail": "corrupt latch file"}

    def save(self, latched: bool, detail: str = "") -> bool:
        """Write the latch state; False (and ``error`` set) if the disk refused."""
        record = {"latched": latched, "wall_time": time.time(), "detail": detail[:200]}
        tmp = self.path.with_suffix(".tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(tmp, "w") as f:
                json.dump(record, f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
            self.error = ""
            return True
        except OSError as e:
            self.error = f"{self.path}: {e.strerror or e}"
            return False
