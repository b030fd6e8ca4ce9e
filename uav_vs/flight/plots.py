"""PNG plots of a closed-loop flight (uav_vs.flight.report.FlightLog), Agg backend.

- `poses.png`: x, y, z and yaw over time of each vision pose, the autopilot's own
  estimate and the truth, as the chapter's Fig. 6 compares them;
- `pose_errors.png`: each source's distance from the truth over time;
- `top_view.png`: the flight seen from above, with the setpoints, the pad and the
  followed target (its truth and the follower's estimate);
- `commands.png`: the controller's velocity commands (section 6).
"""
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from uav_vs.autopilot.frames import wrap_angle
from uav_vs.flight.report import LABELS, SOURCES, FlightLog, interpolate, within

STYLE = {'truth': dict(color='k', lw=1.2, ls='--'), 'ground': dict(color='tab:red', lw=1.0),
         'onboard': dict(color='tab:blue', lw=1.0), 'odom': dict(color='tab:green', lw=1.0),
         'fused': dict(color='tab:purple', lw=1.0)}


def plot_flight(log: FlightLog, out_dir: Path) -> list[Path]:
    """Write every plot into out_dir; return their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = log.takeoff_ns if log.takeoff_ns is not None else int(log.truth.stamps[0])
    paths = []
    for name, draw in (('poses.png', _poses), ('pose_errors.png', _errors),
                       ('top_view.png', _top_view), ('commands.png', _commands)):
        fig = Figure(figsize=(10, 8) if name != 'top_view.png' else (8, 8), layout='constrained')
        FigureCanvasAgg(fig)
        draw(fig, log, t0)
        fig.savefig(out_dir / name, dpi=110)
        paths.append(out_dir / name)
    return paths


def _seconds(stamps: np.ndarray, t0: int) -> np.ndarray:
    return (np.asarray(stamps, np.int64) - t0) * 1e-9


def _events(ax, log: FlightLog, t0: int) -> None:
    """Dotted lines where each setpoint was sent and where LAND was commanded."""
    for event in log.setpoints:
        ax.axvline(_seconds(event.start_ns, t0), color='0.6', ls=':', lw=0.8)
    if log.land_ns is not None:
        ax.axvline(_seconds(log.land_ns, t0), color='tab:purple', ls=':', lw=1.0)


def _poses(fig: Figure, log: FlightLog, t0: int) -> None:
    axes = fig.subplots(4, 1, sharex=True)
    fig.suptitle(f'{log.scenario}: vision pose vs autopilot estimate vs truth (cf. Fig. 6)')
    for name in ('truth', *SOURCES):
        track = getattr(log, name)
        if not len(track):
            continue
        t = _seconds(track.stamps, t0)
        for k, ax in enumerate(axes[:3]):
            ax.plot(t, track.positions[:, k], label=LABELS[name], **STYLE[name])
        axes[3].plot(t, np.degrees(np.unwrap(track.yaws)), **STYLE[name])
    for ax, label in zip(axes, ('x (east), m', 'y (north), m', 'z (up), m', 'yaw, deg')):
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        _events(ax, log, t0)
    axes[0].legend(loc='upper right', fontsize=8)
    axes[-1].set_xlabel('time since the takeoff command, s')


def _errors(fig: Figure, log: FlightLog, t0: int) -> None:
    ax_p, ax_yaw = fig.subplots(2, 1, sharex=True)
    fig.suptitle(f'{log.scenario}: pose error against the simulator truth')
    truth = log.truth
    for name in SOURCES:
        track = getattr(log, name)
        inside = within(truth, track.stamps)
        if not inside.any():
            continue
        p, yaw = interpolate(truth, track.stamps[inside])
        t = _seconds(track.stamps[inside], t0)
        ax_p.plot(t, 100 * np.linalg.norm(track.positions[inside] - p, axis=1),
                  label=LABELS[name], **STYLE[name])
        dyaw = wrap_angle(track.yaws[inside] - yaw)
        ax_yaw.plot(t, np.degrees(dyaw), **STYLE[name])
    ax_p.set_ylabel('position error, cm')
    ax_yaw.set_ylabel('yaw error, deg')
    ax_yaw.set_xlabel('time since the takeoff command, s')
    for ax in (ax_p, ax_yaw):
        ax.grid(alpha=0.3)
        _events(ax, log, t0)
    ax_p.legend(loc='upper right', fontsize=8)


def _top_view(fig: Figure, log: FlightLog, t0: int) -> None:
    ax = fig.subplots()
    ax.set_title(f'{log.scenario}: top view (world ENU)')
    for name in ('truth', 'ground', 'onboard'):
        track = getattr(log, name)
        if len(track):
            style = dict(STYLE[name], lw=0.8) if name != 'truth' else STYLE[name]
            ax.plot(track.positions[:, 0], track.positions[:, 1], label=LABELS[name], **style)
    names: dict[tuple[float, float], list[str]] = {}
    for event in log.setpoints:
        names.setdefault(event.target[:2], []).append(event.name)
    for (x, y), here in names.items():
        ax.plot(x, y, 'o', mfc='none', mec='tab:orange', ms=10)
        ax.annotate(', '.join(here), (x, y), textcoords='offset points', xytext=(8, 6),
                    fontsize=8)
    if len(log.target_truth):
        ax.plot(*log.target_truth.positions[:, :2].T, color='tab:orange', lw=1.0,
                label='target (truth/target)')
    if len(log.target):
        ax.plot(*log.target.positions[:, :2].T, '.', color='tab:brown', ms=2,
                label='target estimate (target/pose)')
    ax.plot(0.0, 0.0, 'k^', ms=8, label='home (takeoff)')
    if log.pad is not None:
        ax.plot(*log.pad, 's', mfc='none', mec='tab:purple', ms=16, mew=2, label='landing pad')
    ax.set_xlabel('x (east), m')
    ax.set_ylabel('y (north), m')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(alpha=0.3)
    ax.legend(loc='best', fontsize=8)


def _commands(fig: Figure, log: FlightLog, t0: int) -> None:
    axes = fig.subplots(4, 1, sharex=True)
    fig.suptitle(f'{log.scenario}: cmd_vel of the fuzzy controller (world ENU)')
    c = log.commands
    t = _seconds(c.received, t0)
    values = (c.linear[:, 0], c.linear[:, 1], c.linear[:, 2], c.yaw_rate)
    labels = ('vx (east), m/s', 'vy (north), m/s', 'vz (up), m/s', 'yaw rate, rad/s')
    for ax, v, label in zip(axes, values, labels):
        ax.plot(t, v, color='tab:orange', lw=1.0)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        _events(ax, log, t0)
    axes[-1].set_xlabel('time since the takeoff command, s')
