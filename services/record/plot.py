"""A picture of a run file: the ego's path with its scans drawn in the world at a few instants,
the obstacle cars' paths, and the commands over time (``racecav replay run.mcap --plot-only PNG``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from racecav.common import keys
from racecav.common.codec import DecodeError, decode
from racecav.common.messages import DriveCommand, ObstacleStates, Scan, VehicleState


def plot_run(path: str | Path, png: str | Path, car: str | None = None, world: str | None = None,
             n_scans: int = 4, new_cmds: dict | None = None) -> Path:
    """Draw run file ``path`` into ``png``.

    :param car: the car to draw (default: the file's only car).
    :param world: a world whose walls to draw under the paths (None: no walls).
    :param n_scans: scans drawn as points in the world frame, evenly spread over the run.
    :param new_cmds: replayed commands by (scan seq, scan stamp), drawn over the recorded ones.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from racecav.common.vehicle import load_car
    from racecav.services.record.mcapfile import RunFileError, read_raw, run_cars

    samples = read_raw(path)
    cars = run_cars(samples)
    car = car or (cars[0] if len(cars) == 1 else None)
    if car is None:
        raise RunFileError(f"{path}: scans of {len(cars)} cars: name one")
    want = {keys.topic(car, k): c for k, c in ((keys.SCAN, Scan), (keys.STATE, VehicleState),
                                                 (keys.CMD, DriveCommand), (keys.OBSTACLES, ObstacleStates))}
    got: dict[type, list] = {c: [] for c in want.values()}
    for s in samples:
        cls = want.get(s.key)
        if cls is not None:
            try:
                got[cls].append(decode(s.payload, cls))
            except DecodeError:
                pass
    states, scans, cmds, obs = got[VehicleState], got[Scan], got[DriveCommand], got[ObstacleStates]
    fig, (ax, axc) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.2, 1]})
    if world:
        from racecav.common.world import load_world, plot_world

        plot_world(load_world(world), ax=ax, show_centerline=False)
    if states:
        xy = np.array([(s.x, s.y) for s in states])
        ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=2, label=f"ego ({car})")
    tracks: dict[int, list] = {}
    for o in obs:
        for ob in o.obstacles:
            tracks.setdefault(ob.id, []).append((ob.x, ob.y))
    for i, (oid, pts) in enumerate(sorted(tracks.items())):
        p = np.array(pts)
        ax.plot(p[:, 0], p[:, 1], "-", color="tab:red", lw=1.5, label="obstacle cars" if i == 0 else None)
    # scans in the world: the ego pose of the same stamp (the sim stamps both alike), mount from the car file
    mount = load_car("slash").lidar_mount
    by_stamp = {s.stamp_ns: s for s in states}
    picks = [sc for sc in scans if sc.stamp_ns in by_stamp]
    for k, sc in enumerate(picks[:: max(1, len(picks) // n_scans)][:n_scans]):
        st = by_stamp[sc.stamp_ns]
        a = sc.angles() + mount.yaw
        r = np.where(np.isfinite(sc.ranges), sc.ranges, np.nan)
        lx, ly = mount.x + r * np.cos(a), mount.y + r * np.sin(a)
        c, s_ = np.cos(st.yaw), np.sin(st.yaw)
        ax.plot(st.x + c * lx - s_ * ly, st.y + s_ * lx + c * ly, ".", ms=2, color=f"C{2 + k}",
                label=f"scan at t = {(sc.stamp_ns - scans[0].stamp_ns) / 1e9:.1f} s")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(Path(path).name)
    if cmds:
        t0 = scans[0].stamp_ns if scans else cmds[0].stamp_ns
        t = np.array([(c.stamp_ns - t0) / 1e9 for c in cmds])
        axc.plot(t, [c.a_throttle for c in cmds], "-", color="tab:green", label="a_T (recorded)")
        axc.plot(t, [c.a_steer for c in cmds], "-", color="tab:purple", label="a_delta (recorded)")
        if new_cmds:
            pairs = [(c, new_cmds.get((c.scan_seq, c.scan_stamp_ns))) for c in cmds]
            tn = np.array([(c.stamp_ns - t0) / 1e9 for c, n in pairs if n is not None])
            new = [n for _c, n in pairs if n is not None]
            axc.plot(tn, [n.a_throttle for n in new], "--", color="tab:olive", label="a_T (replayed)")
            axc.plot(tn, [n.a_steer for n in new], "--", color="tab:pink", label="a_delta (replayed)")
        axc.set_xlabel("time (s)")
        axc.set_ylabel("normalised action")
        axc.set_ylim(-1.05, 1.05)
        axc.legend(loc="best", fontsize=8)
        axc.set_title(f"commands ({cmds[0].source})")
    fig.tight_layout()
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png
