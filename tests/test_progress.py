"""Progress on a loop that crosses itself: both backends score a car that drives straight through
the figure eight's crossing (and on along its arm) with the distance it drove. A tracker that
takes the globally nearest centerline point jumps to the other arm at the crossing, half a lap
away, and scored such a drive about -59 m (PyBullet, before sim/progress.py)."""

import numpy as np
import pytest

from racecav.sim.bullet_world import BulletWorld
from racecav.sim.fast_world import FastWorld
from racecav.sim.progress import LoopProgress, dense_centerline
from racecav.common.world import load_world

# the figure eight's east arm runs along y = 0 through the crossing at the origin; the ego starts
# 3 m before it, 0.3 m left of the centerline (nearer the south arm while within 0.3 m of the crossing)
START = (-3.0, 0.3, 0.0)
SPEED = 1.5
STEPS = 45  # 4.5 s: about 6.5 m, through the crossing and on
FIGURE8 = """
name = "figure8-empty"
world = "figure8"
duration_s = 10.0
[traffic]
cars = 0
[success]
min_progress_m = 5.0
"""


def _drive(step, state) -> tuple[float, list]:
    xs = [state()[0]]
    for _ in range(STEPS):
        step()
        xs.append(state()[0])
    return xs[-1] - xs[0], xs


def test_pybullet_progress_through_the_crossing(tmp_path):
    sc = tmp_path / "figure8-empty.toml"
    sc.write_text(FIGURE8)
    w = BulletWorld(str(sc))
    w.reset(seed=0, options={"agent_pose": START, "agent_speed": SPEED})
    driven, xs = _drive(lambda: w.step(np.array([[0.6, 0.0]])), lambda: w.car_state(0))
    assert xs[0] < -2.5 and xs[-1] > 2.0, xs  # through the crossing
    assert w.progress()[0] == pytest.approx(driven, abs=0.1)


def test_fast_world_progress_through_the_crossing():
    fw = FastWorld(n_envs=1, world="figure8", n_obstacles=0)
    fw.reset(seed=0)
    fw.set_state(0, 0, x=START[0], y=START[1], yaw=START[2], v=SPEED)
    driven, xs = _drive(lambda: fw.step(np.array([[0.6, 0.0]]), observe=False), lambda: fw.agent_state()[0])
    assert xs[0] < -2.5 and xs[-1] > 2.0, xs
    assert fw.progress()[0] == pytest.approx(driven, abs=0.1)


def test_tracker_stays_on_its_arm_where_the_nearest_point_jumps():
    """The tracker alone, on poses along the east arm with a small lateral offset: the world's global
    nearest point jumps half a lap at the crossing, the tracker moves by the distance."""
    world = load_world("figure8")
    track = LoopProgress(dense_centerline(world))
    xs = np.arange(-3.0, 3.01, 0.1)
    track.place(0, 0, xs[0], 0.04)
    moved = sum(float(track.update(np.array([[x]]), np.array([[0.04]]))[0]) for x in xs[1:])
    assert moved == pytest.approx(6.0, abs=0.06)
    s = world.progress(xs, np.full_like(xs, 0.04))
    assert np.abs(np.diff(s)).max() > world.length / 3  # what the global search does at the crossing
