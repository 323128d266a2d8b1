"""Progress along a loop world's centerline, for both backends.

Each car keeps an index into a dense centerline table (a point every CENTERLINE_DS metres) and
moves it by a local search around its last value, at most WINDOW_BACK points back and
WINDOW_FWD ahead per update. The globally nearest centerline point is no measure of progress on a
loop that crosses itself (the figure eight): at the crossing it jumps to the other arm, tens of
metres along the loop, and a car that drives through would be scored minus that. Progress is
counted in table points, so it is resolved to CENTERLINE_DS (the same in both backends).
"""

from __future__ import annotations

import numpy as np

from racecav.sim import fast_kernels as K

CENTERLINE_DS = 0.05
"""m, spacing of the dense centerline table (resets, traffic, progress)."""
WINDOW_BACK, WINDOW_FWD = 10, 40
"""Table points searched behind / ahead of a car's last index per update (0.5 m / 2 m: more than a
car moves in a control period either way, less than the distance between the arms of a crossing)."""


def dense_centerline(world, ds: float = CENTERLINE_DS) -> np.ndarray:
    """(K, 4) table x, y, yaw, curvature every ``ds`` metres along the world's closed centerline."""
    pts = np.asarray(world.centerline, dtype=np.float64)
    closed = np.vstack([pts, pts[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(s[-1] / ds), 8)
    q = np.linspace(0.0, s[-1], n, endpoint=False)
    x = np.interp(q, s, closed[:, 0])
    y = np.interp(q, s, closed[:, 1])
    dx = np.roll(x, -1) - np.roll(x, 1)
    dy = np.roll(y, -1) - np.roll(y, 1)
    yaw = np.arctan2(dy, dx)
    dyaw = np.angle(np.exp(1j * (np.roll(yaw, -1) - yaw)))
    step = s[-1] / n
    kap = dyaw / step
    win = max(int(0.3 / step), 1)  # smooth over ~0.6 m (the polyline's corners are kinks)
    kernel = np.ones(2 * win + 1) / (2 * win + 1)
    kap = np.convolve(np.concatenate([kap[-win:], kap, kap[:win]]), kernel, mode="valid")
    return np.stack([x, y, yaw, kap], axis=1)


class LoopProgress:
    """Every car's station on a closed centerline, tracked locally (N worlds x C cars).

    :param table: dense_centerline of the world. :param shape: (N, C).
    """

    def __init__(self, table: np.ndarray, shape: tuple[int, int] = (1, 1)):
        self.table = table
        self.ds = float(np.hypot(*(table[1, :2] - table[0, :2]))) if len(table) > 1 else 1.0
        self.lap = len(table) * self.ds
        self.idx = np.zeros(shape, dtype=np.int64)
        """(N, C) index of each car's station in ``table`` (kernels that place cars write it too)."""

    def place(self, n: int, c: int, x: float, y: float) -> None:
        """A car was put at (x, y): its station is the globally nearest point (a reset)."""
        self.idx[n, c] = K.global_nearest(float(x), float(y), self.table)

    def update(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Move every car's station to (x, y) (N, C) by the local search; returns the first car's
        (the ego's) signed arc length moved (N,), wrapped over the lap."""
        prev = self.idx[:, 0].copy()
        K.nearest_index(x, y, self.table, self.idx, WINDOW_BACK, WINDOW_FWD)
        return ((self.idx[:, 0] - prev) * self.ds + self.lap / 2) % self.lap - self.lap / 2
