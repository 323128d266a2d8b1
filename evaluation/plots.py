"""Figures of the evaluation (matplotlib, Agg backend): trajectories like the paper's Figure 4 and
the success-rate bar chart of Table 1."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from racecav.evaluation.results import Trial


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _cmap(name: str):
    """A matplotlib colormap without its near-white start (early points stay visible)."""
    import matplotlib
    from matplotlib.colors import ListedColormap

    return ListedColormap(matplotlib.colormaps[name](np.linspace(0.3, 1.0, 256)))


def _outline(ax, x, y, yaw, length, width, color, ls="-"):
    from racecav.evaluation.metrics import box_corners

    c = box_corners([x], [y], [yaw], length, width)[0]
    c = np.vstack([c, c[:1]])
    ax.plot(c[:, 0], c[:, 1], color=color, lw=1.0, ls=ls)


def _save(plt, fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def outcome(trial: Trial) -> str:
    if trial.success:
        return "success"
    if trial.collided:
        return f"contact ({trial.contact_with}) at {trial.contact_time_s:.1f} s"
    return f"no contact, progress {trial.progress_m:.1f} m < min"


def plot_trajectories(panels: list[tuple[Trial, str]], walls: list[np.ndarray], path: Path,
                      title: str = "", car_size: tuple[float, float] = (0.55, 0.3)) -> Path:
    """Ego (green) and obstacle (red) paths, coloured by time, one panel per trial.

    :param panels: (trial with trajectory, panel title) pairs.
    :param walls: per panel, the world's wall segments (M, 4) to draw as the road edges.
    :param car_size: ego length, width (m) for the footprints at the start and at the end.
    """
    plt = _plt()
    n = len(panels)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n + 1.0, 4.6), squeeze=False)
    sc = None
    tmax = max((max(p[0].trajectory.t) for p in panels if p[0].trajectory and p[0].trajectory.t), default=1.0)
    for ax, (trial, name), wl in zip(axes[0], panels, walls):
        tr = trial.trajectory
        if tr is None:
            ax.set_title(f"{name}\n(no trajectory recorded)")
            continue
        t = np.asarray(tr.t)
        ego = np.asarray(tr.ego)
        pts = [ego[:, :2]] + [np.asarray(o)[:, :2] for o in tr.obstacles]
        allp = np.vstack(pts)
        centre = (allp.min(0) + allp.max(0)) / 2
        half = max(float((allp.max(0) - allp.min(0)).max()) / 2 + 0.8, 2.0)
        lo, hi = centre - half, centre + half  # square window around the action
        for x0, y0, x1, y1 in np.asarray(wl):
            ax.plot([x0, x1], [y0, y1], color="0.35", lw=1.5)
        for o in tr.obstacles:
            o = np.asarray(o)
            ax.scatter(o[:, 0], o[:, 1], c=t, cmap=_cmap("Reds"), vmin=0, vmax=tmax, s=9, zorder=3)
            _outline(ax, *o[0], *car_size, "darkred", ":")
            _outline(ax, *o[-1], *car_size, "darkred")
        sc = ax.scatter(ego[:, 0], ego[:, 1], c=t, cmap=_cmap("Greens"), vmin=0, vmax=tmax, s=9, zorder=4)
        _outline(ax, *ego[0], *car_size, "darkgreen", ":")
        _outline(ax, *ego[-1], *car_size, "darkgreen")
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        if ax is axes[0][0]:
            ax.set_ylabel("y (m)")
        gap = "" if trial.min_gap_m is None else f", min gap {trial.min_gap_m:.2f} m"
        ax.set_title(f"{name}, seed {trial.seed}\n{outcome(trial)}{gap}", fontsize=8.5)
    if sc is not None:
        cb = fig.colorbar(sc, ax=axes[0].tolist(), shrink=0.8, pad=0.02)
        cb.set_label("time (s); ego green, obstacle red")
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(plt, fig, path)


def plot_success_bars(rows: list[tuple[str, list[tuple[float | None, tuple[float, float] | None, float | None]]]],
                      scenarios: list[str], path: Path, title: str = "") -> Path:
    """Grouped bars: success rate per scenario and controller, 95 % CI whiskers, paper values as
    black diamonds.

    :param rows: (controller label, per scenario (rate, ci95, paper rate or None)).
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.2))
    width = 0.8 / max(len(rows), 1)
    x = np.arange(len(scenarios))
    paper_labelled = False
    for k, (label, cells) in enumerate(rows):
        xs = x - 0.4 + width * (k + 0.5)
        rates = [100 * (c[0] or 0.0) for c in cells]
        # max(0, ...): a Wilson bound equals the rate at 0 or 1 up to rounding (-1e-17 is an error here)
        lo = [max(0.0, 100 * ((c[0] or 0) - c[1][0])) if c[1] else 0 for c in cells]
        hi = [max(0.0, 100 * (c[1][1] - (c[0] or 0))) if c[1] else 0 for c in cells]
        ax.bar(xs, rates, width * 0.9, label=label, yerr=[lo, hi], capsize=3)
        papers = [(xx, 100 * c[2]) for xx, c in zip(xs, cells) if c[2] is not None]
        if papers:
            ax.scatter(*zip(*papers), marker="D", color="black", s=18, zorder=5,
                       label=None if paper_labelled else "paper (10 hardware trials)")
            paper_labelled = True
    ax.set_xticks(x, scenarios)
    ax.set_ylim(0, 105)
    ax.set_ylabel("success rate (%)")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if title:
        ax.set_title(title, fontsize=10)
    return _save(plt, fig, path)


def plot_paths(name: str, paths: dict, out: Path) -> Path:
    """In-process trials' ego (coloured by outcome) and obstacle paths through the intersection,
    one panel per scenario (``paths``: scenario -> the ``paths`` of evaluation/inprocess.eval_scenario)."""
    from racecav.common.world import load_world

    plt = _plt()

    walls = load_world("intersection").walls
    fig, axes = plt.subplots(1, len(paths), figsize=(5 * len(paths), 5))
    for ax, (sc, trials) in zip(np.atleast_1d(axes), paths.items()):
        for x0, y0, x1, y1 in walls:
            ax.plot([x0, x1], [y0, y1], color="0.4", lw=1)
        for tr in trials:
            xy = np.asarray(tr["xy"])
            if not len(xy):
                continue
            c = "tab:green" if tr["success"] else ("tab:red" if tr["contact"] else "tab:orange")
            ax.plot(xy[:, 0], xy[:, 1], color=c, lw=1.2)
            ax.plot(xy[-1, 0], xy[-1, 1], "o", color=c, ms=3)
            for j in range(2, xy.shape[1], 2):
                ax.plot(xy[:, j], xy[:, j + 1], color="tab:blue", lw=0.6, alpha=0.5)
        ax.set(title=Path(sc).stem, xlim=(-8.5, 8.5), ylim=(-8.5, 8.5), aspect="equal")  # a file's stem, not its path
    n = max(len(t) for t in paths.values())
    fig.suptitle(f"{name}: ego paths, first {n} trials: green success, red contact, orange no contact but "
                 "short of min progress; blue obstacle", fontsize=9)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def plot_degradation(curves: dict, path: Path, title: str = "") -> Path:
    """One panel per sweep: success rate against the perturbation's size, a line per controller,
    95 % Wilson whiskers.

    :param curves: sweep -> (x label, {controller label: [(x, (successes, trials) or None), ...]}).
    """
    from racecav.evaluation.results import wilson

    plt = _plt()
    fig, axes = plt.subplots(1, len(curves), figsize=(4.2 * len(curves), 3.6), sharey=True)
    for ax, (sweep, (xlabel, lines)) in zip(np.atleast_1d(axes), curves.items()):
        for label, pts in lines.items():
            pts = [(x, p) for x, p in pts if p is not None and p[1]]
            if not pts:
                continue
            xs = [x for x, _ in pts]
            rates = [100 * ok / n for _, (ok, n) in pts]
            ci = [wilson(ok, n) for _, (ok, n) in pts]
            lo = [max(0.0, r - 100 * c[0]) for r, c in zip(rates, ci)]
            hi = [max(0.0, 100 * c[1] - r) for r, c in zip(rates, ci)]
            ax.errorbar(xs, rates, yerr=[lo, hi], marker="o", capsize=3, label=label)
        ax.set_xlabel(xlabel)
        ax.set_title(sweep, fontsize=10)
        ax.set_ylim(0, 105)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("success rate (%)")
    np.atleast_1d(axes)[-1].legend(fontsize=8, loc="lower left")
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(plt, fig, path)
