"""Pictures of positioners: snapshots of arms, capsules and targets, and animations of runs.

Everything draws on matplotlib axes (``Agg`` is enough; no screen is needed, and it is chosen
only when no backend is: notebooks show their figures inline). Colliding positioners are drawn
in red.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import matplotlib

# A non-interactive backend only where nobody chose one: Jupyter (ipykernel sets MPLBACKEND to
# its inline backend) and a user's own choice keep theirs, so figures show in notebooks.
if "MPLBACKEND" not in os.environ and "ipykernel" not in sys.modules and "matplotlib.pyplot" not in sys.modules:
    matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure

from fiberplan._atomic import atomic_path
from fiberplan.geometry import capsule_segments, min_pair_clearance
from fiberplan.kinematics import elbow_positions, fiber_positions
from fiberplan.scenario import Scenario
from fiberplan.trajectory import PlanResult

_ARC_POINTS = 10
_OK_COLOUR = "#4a7fb5"
_HIT_COLOUR = "#d62728"
_SHORT_COLOURS = {"deadlocked": "#ff7f0e", "unfinished": "#9467bd", "failed": "#8c564b", "infeasible": "#7f7f7f", "locked": "#17becf",
                  "displaced": "#e377c2"}
"""Outcomes marked on snapshots and animations (a square around the base, the id beside it)."""


def _capsule_polygons(start: np.ndarray, end: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Outline polygons ``(M, 2 * _ARC_POINTS, 2)`` of capsules with segments ``start -> end``."""
    direction = end - start
    length = np.linalg.norm(direction, axis=-1, keepdims=True)
    unit = np.where(length > 1e-12, direction / np.maximum(length, 1e-12), np.array([1.0, 0.0]))
    heading = np.arctan2(unit[:, 1], unit[:, 0])
    arc = np.linspace(-np.pi / 2, np.pi / 2, _ARC_POINTS)
    ang_end = heading[:, None] + arc[None, :]
    ang_start = heading[:, None] + np.pi + arc[None, :]
    r = radius[:, None]
    cap_end = end[:, None, :] + r[..., None] * np.stack([np.cos(ang_end), np.sin(ang_end)], axis=-1)
    cap_start = start[:, None, :] + r[..., None] * np.stack([np.cos(ang_start), np.sin(ang_start)], axis=-1)
    return np.concatenate([cap_end, cap_start], axis=1)


def colliding_rows(scenario: Scenario, joints: np.ndarray) -> np.ndarray:
    """Rows of positioners that collide with a neighbour in configuration ``joints``."""
    pairs = scenario.pairs
    if len(pairs) == 0:
        return np.zeros(0, dtype=np.int64)
    clearance = min_pair_clearance(scenario.instrument, scenario.base_xy, scenario.orient, joints, pairs)
    return np.unique(pairs[clearance < 0.0].ravel())


class _Frame:
    """Artists of one snapshot, updatable for animations."""

    def __init__(self, ax: Axes, scenario: Scenario, show_targets: bool, outcome: np.ndarray | None = None) -> None:
        self.ax = ax
        self.scenario = scenario
        inst = scenario.instrument
        n = scenario.n_positioners
        self.radii = np.tile([c.radius_mm for c in inst.capsules], n)
        theta = np.linspace(0, 2 * np.pi, 48)
        rings = scenario.base_xy[:, None, :] + inst.reach_max_mm * np.stack([np.cos(theta), np.sin(theta)], axis=-1)[None]
        ax.add_collection(LineCollection(list(rings), colors="#cccccc", linewidths=0.4, zorder=0))
        ax.plot(scenario.base_xy[:, 0], scenario.base_xy[:, 1], ".", color="#888888", markersize=2, zorder=1)
        if show_targets:
            tx = scenario.target_xy[scenario.has_target]
            ax.plot(tx[:, 0], tx[:, 1], "x", color="#2ca02c", markersize=3, mew=0.8, zorder=4, label="target")
        self.capsules = PolyCollection([], facecolors=_OK_COLOUR, edgecolors="none", alpha=0.55, zorder=2)
        ax.add_collection(self.capsules)
        self.arms = LineCollection([], colors="#222222", linewidths=0.6, zorder=3)
        ax.add_collection(self.arms)
        (self.alarm,) = ax.plot([], [], "o", mfc="none", mec=_HIT_COLOUR, ms=14, mew=1.2, zorder=5)
        if outcome is not None:  # positioners not reached, marked with their outcome
            for kind, colour in _SHORT_COLOURS.items():
                rows = np.flatnonzero(np.asarray(outcome) == kind)
                if len(rows):
                    ax.plot(scenario.base_xy[rows, 0], scenario.base_xy[rows, 1], "s", mfc="none", mec=colour, ms=9, mew=1.0, zorder=5,
                            label=f"{kind} ({len(rows)})")
                    if len(rows) <= 40:
                        for k in rows.tolist():
                            ax.annotate(str(scenario.ids[k]), scenario.base_xy[k], fontsize=6, color=colour, xytext=(3, 3),
                                        textcoords="offset points", zorder=6)
            if any(np.isin(np.asarray(outcome), list(_SHORT_COLOURS))):
                ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
        lo = scenario.base_xy.min(axis=0) - inst.extent_mm
        hi = scenario.base_xy.max(axis=0) + inst.extent_mm
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")

    def update(self, joints: np.ndarray, title: str) -> int:
        sc = self.scenario
        inst = sc.instrument
        start, end = capsule_segments(inst, sc.base_xy, sc.orient, joints)
        polys = _capsule_polygons(start.reshape(-1, 2), end.reshape(-1, 2), self.radii)
        hit = colliding_rows(sc, joints)
        colours = np.full(sc.n_positioners, _OK_COLOUR, dtype=object)
        colours[hit] = _HIT_COLOUR
        self.capsules.set_verts(list(polys))
        self.capsules.set_facecolor(np.repeat(colours, len(inst.capsules)).tolist())
        elbow = elbow_positions(inst, sc.base_xy, sc.orient, joints)
        fiber = fiber_positions(inst, sc.base_xy, sc.orient, joints)
        segs = np.concatenate([np.stack([sc.base_xy, elbow], axis=1), np.stack([elbow, fiber], axis=1)])
        self.arms.set_segments(list(segs))
        self.alarm.set_data(sc.base_xy[hit, 0], sc.base_xy[hit, 1])
        self.ax.set_title(title + (f"   {len(hit)} positioners colliding" if len(hit) else ""), fontsize=9)
        return len(hit)


def plot_snapshot(
    scenario: Scenario,
    joints: np.ndarray | None = None,
    *,
    ax: Axes | None = None,
    title: str = "",
    show_targets: bool = True,
    outcome: np.ndarray | None = None,
) -> Figure:
    """Draw arms, capsules (red where colliding), patrol circles and targets; with ``outcome``,
    the positioners not reached are marked by their outcome (deadlocked, infeasible, locked...).

    Args:
        scenario: the positioners.
        joints: ``(N, 2)`` configuration (rad); the start configuration by default.
        ax: axes to draw on (a new figure by default).
        title: figure title.
        show_targets: mark the targets.
        outcome: ``(N,)`` outcomes (``PlanResult.outcome``) to mark those not reached.
    """
    if ax is None:
        fig, ax = plt.subplots(figsize=(7, 7))
    else:
        fig = ax.figure  # type: ignore[assignment]
    frame = _Frame(ax, scenario, show_targets, outcome)
    frame.update(scenario.start if joints is None else joints, title)
    return fig  # type: ignore[return-value]


def default_snapshot_time(result: PlanResult, collision_times: list[float]) -> float:
    """The instant worth showing: the first collision if there is one, else the end."""
    return min(collision_times) if collision_times else result.trajectory.duration_s


def save_snapshot(result: PlanResult, out: str | Path, t: float, dpi: int = 150) -> Path:
    """Write a PNG snapshot of a run at time ``t``."""
    joints = result.trajectory.at(t)
    fig = plot_snapshot(
        result.scenario,
        joints,
        title=f"{result.planner} | {result.scenario.instrument.name} | N={result.scenario.n_positioners} | t = {t:.3f} s",
        outcome=result.outcome,
    )
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=dpi, format=out.suffix.lstrip(".") or "png", bbox_inches="tight")
    plt.close(fig)
    return out


def save_animation(result: PlanResult, out: str | Path, *, fps: int = 20, max_frames: int = 120, dpi: int = 90) -> Path:
    """Write an animation (GIF; MP4 if ``out`` ends in .mp4 and ffmpeg is present) of a run."""
    out = Path(out)
    traj = result.trajectory
    n_frames = int(min(max_frames, max(2, len(traj.times))))
    frame_times = np.linspace(0.0, traj.duration_s, n_frames)
    fig, ax = plt.subplots(figsize=(6, 6))
    frame = _Frame(ax, result.scenario, show_targets=True, outcome=result.outcome)
    label = f"{result.planner} | {result.scenario.instrument.name} | N={result.scenario.n_positioners}"

    def draw(k: int) -> list:
        frame.update(traj.at(float(frame_times[k])), f"{label} | t = {frame_times[k]:.2f} s")
        return [frame.capsules, frame.arms, frame.alarm]

    anim = FuncAnimation(fig, draw, frames=n_frames, blit=False)
    with atomic_path(out) as tmp:
        if out.suffix.lower() == ".mp4":
            from matplotlib.animation import FFMpegWriter

            anim.save(str(tmp), writer=FFMpegWriter(fps=fps), dpi=dpi)
        else:
            anim.save(str(tmp), writer=PillowWriter(fps=fps), dpi=dpi)
    plt.close(fig)
    return out


def plot_joint_profiles(result: PlanResult, ids: list[int] | None = None, *, max_positioners: int = 4) -> Figure:
    """Joint angle and joint speed profiles of chosen positioners (as reference 000, figs. 7-8).

    Args:
        result: a planned run.
        ids: positioner ids to draw; default the ``max_positioners`` with the longest moves.
        max_positioners: how many to pick when ``ids`` is not given.
    """
    scenario, traj = result.scenario, result.trajectory
    if ids is None:
        travel = np.abs(scenario.target - scenario.start).sum(axis=1)
        rows = np.argsort(-travel)[:max_positioners]
    else:
        rows = np.array([scenario.index_of(i) for i in ids])
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    dt = np.diff(traj.times)
    speed = np.diff(traj.joints, axis=0) / dt[:, None, None]
    limits = scenario.instrument.speeds_rad_s
    for col, joint in enumerate(("alpha", "beta")):
        for row in rows:
            label = f"positioner {scenario.ids[row]}"
            axes[0, col].plot(traj.times, np.degrees(traj.joints[:, row, col]), label=label)
            axes[1, col].step(traj.times[:-1], np.degrees(speed[:, row, col]), where="post", label=label)
        for sign in (-1, 1):
            axes[1, col].axhline(sign * np.degrees(limits[col]), color="#999999", lw=0.8, ls="--")
        axes[0, col].set_ylabel(f"{joint} [deg]")
        axes[1, col].set_ylabel(f"{joint} speed [deg/s]")
        axes[1, col].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{result.planner} | {scenario.instrument.name} | joint profiles", fontsize=10)
    fig.tight_layout()
    return fig


def plot_motor_profiles(result: PlanResult, profiles: Any, ids: list[int] | None = None, *, max_positioners: int = 3) -> Figure:
    """Planned samples (thin) against their motor profiles (thick): joint angles and speeds of
    chosen positioners (as reference 004, fig. 11.10), the instrument's speed range shaded.

    Args:
        result: the planned run the profiles were made from.
        profiles: :class:`fiberplan.profiles.Profiles` of ``result``.
        ids: positioner ids to draw; default the ``max_positioners`` with the most segments.
        max_positioners: how many to pick when ``ids`` is not given.
    """
    scenario, traj = result.scenario, result.trajectory
    if ids is None:
        rows = np.argsort(-profiles.segment_counts().sum(axis=1), kind="stable")[:max_positioners]
    else:
        rows = np.array([scenario.index_of(i) for i in ids])
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharex=True)
    speed = np.diff(traj.joints, axis=0) / np.diff(traj.times)[:, None, None]
    inst = scenario.instrument
    top = inst.speeds_rad_s
    low = inst.motors.min_speed_rad_s
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for col, joint in enumerate(("alpha", "beta")):
        for n, row in enumerate(rows):
            colour = colours[n % len(colours)]
            axes[0, col].plot(traj.times, np.degrees(traj.joints[:, row, col]), color=colour, lw=0.8, alpha=0.6)
            axes[1, col].step(traj.times[:-1], np.degrees(speed[:, row, col]), where="post", color=colour, lw=0.8, alpha=0.6)
            prof = profiles.joints.get((int(row), col))
            count = 0 if prof is None else len(prof.durations_s)
            label = f"positioner {scenario.ids[row]}: {count} segment{'s' if count != 1 else ''}"
            if prof is None:
                axes[0, col].plot([], [], color=colour, lw=2.2, ls="--", label=label)
                continue
            t_knot, q_knot = prof.knots()
            axes[0, col].plot(t_knot, np.degrees(q_knot), color=colour, lw=2.2, ls="--", marker="o", ms=3, label=label)
            axes[1, col].step(t_knot, np.degrees(np.append(prof.speeds_rad_s, 0.0)), where="post", color=colour, lw=2.2, ls="--")
        for sign in (-1, 1):
            axes[1, col].axhline(sign * np.degrees(top[col]), color="#999999", lw=0.8, ls="--")
            if low is not None:
                axes[1, col].axhspan(0, sign * np.degrees(low[col]), color="#dddddd", zorder=0)
        axes[0, col].set_ylabel(f"{joint} [deg]")
        axes[1, col].set_ylabel(f"{joint} speed [deg/s]")
        axes[1, col].set_xlabel("time [s]")
        axes[0, col].legend(fontsize=7)
    fig.suptitle(f"{result.planner} | {inst.name} | planned samples (thin) and motor profiles (dashed)"
                 f"{'; grey: below the minimum speed' if low is not None else ''}", fontsize=10)
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------------------ study plots


def plot_rates(rates_frame: Any, x: str, *, hue: str | None = "planner", rate: str = "deadlock", ax: Axes | None = None) -> Figure:
    """Deadlock (or success) rate against a parameter, with Wilson-interval error bars.

    Args:
        rates_frame: output of :func:`fiberplan.studies.rates` grouped by ``x`` (and ``hue``).
        x: column on the horizontal axis (e.g. ``n_positioners``, ``setting.lambda_ratio``).
        hue: column separating the curves (e.g. ``planner``), or None.
        rate: ``deadlock`` or ``success``.
    """
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.5, 4))
    else:
        fig = ax.figure  # type: ignore[assignment]
    groups = [(None, rates_frame)] if hue is None else list(rates_frame.groupby(hue))
    for label, group in groups:
        group = group.sort_values(x)
        value = group[f"{rate}_rate"].to_numpy()
        err = np.clip(np.vstack([value - group[f"{rate}_lo"].to_numpy(), group[f"{rate}_hi"].to_numpy() - value]), 0.0, None)
        ax.errorbar(group[x], value, yerr=err, marker="o", capsize=3, label=None if label is None else str(label))
    ax.set_xlabel(x)
    ax.set_ylabel(f"{rate} rate (95 % Wilson interval)")
    if hue is not None:
        ax.legend(title=hue)
    ax.grid(alpha=0.3)
    return fig  # type: ignore[return-value]


def plot_scaling(frame: Any, *, hue: str = "planner", ax: Axes | None = None) -> Figure:
    """Plan wall time against the number of positioners on log-log axes (median and range)."""
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.5, 4))
    else:
        fig = ax.figure  # type: ignore[assignment]
    ok = frame[frame["status"] == "ok"]
    for label, group in ok.groupby(hue):
        stats = group.groupby("n_positioners")["plan_wall_s"].agg(["median", "min", "max"]).reset_index()
        ax.plot(stats["n_positioners"], stats["median"], "o-", label=str(label))
        ax.fill_between(stats["n_positioners"], stats["min"], stats["max"], alpha=0.2)
    n = np.array(sorted(ok["n_positioners"].unique()), dtype=float)
    if len(n) > 1:
        ref = ok.groupby("n_positioners")["plan_wall_s"].median().to_numpy()
        ax.plot(n, ref[0] * n / n[0], "k--", lw=0.8, label="linear")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("positioners")
    ax.set_ylabel("plan wall time [s]")
    ax.legend()
    ax.grid(alpha=0.3, which="both")
    return fig  # type: ignore[return-value]


def plot_makespan_ratio(frame: Any, *, by: str = "planner", ax: Axes | None = None) -> Figure:
    """Distribution of makespan / lower bound per group (box plot over runs)."""
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.5, 4))
    else:
        fig = ax.figure  # type: ignore[assignment]
    ok = frame[(frame["status"] == "ok") & np.isfinite(frame["makespan_over_bound"])]
    labels, data = [], []
    for label, group in ok.groupby(by):
        labels.append(str(label))
        data.append(group["makespan_over_bound"].to_numpy())
    if data:
        ax.boxplot(data, tick_labels=labels)
    ax.axhline(1.0, color="#999999", ls="--", lw=0.8)
    ax.set_ylabel("makespan / lower bound")
    ax.set_xlabel(by)
    ax.grid(alpha=0.3, axis="y")
    return fig  # type: ignore[return-value]


def save_figure(fig: Figure, out: str | Path, dpi: int = 150) -> Path:
    """Save a figure atomically and close it."""
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format=out.suffix.lstrip(".") or "png")
    plt.close(fig)
    return out
