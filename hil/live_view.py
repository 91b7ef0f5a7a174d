"""A live view of a HIL run (``eso-hil run --plot``): matplotlib, four panels.

- path: the reference path and the vehicle's trace, with its current pose;
- e_Y: the lateral deviation from the path over time (``hil.metrics``' definition);
- steering: the ECU's STEER_ANGLE_CMD per control cycle and the plant's STEER_ANGLE;
- mode and task time: CTRL_MODE per control cycle and CTRL_DIAG.CYCLE_TIME_US.

:class:`LiveSampler` is the time master's ``on_tick`` callback (``hil.rig.Rig.run``): it
only reads the plant node's vehicle and the ECU frame monitor's lists (it sends nothing,
changes no state), every ``sample_period_ms`` of virtual time, into bounded buffers, so a
lockstep run gives the same frames with and without the view. :class:`LiveFigure` draws
the buffers; :class:`LiveView` joins the two and redraws at most every
``min_interval_s`` of wall clock (and never more than ``draw_share`` of the wall clock:
the interval grows with the measured cost of a redraw). A redraw runs in the time
master's thread (a GUI lives in the main thread): in lockstep it only slows the run down;
in real time it holds the plant's ticks for its duration (tens of ms), which the
master's absolute deadlines then catch up.

Without a display (no ``DISPLAY`` / ``WAYLAND_DISPLAY``, or ``MPLBACKEND=Agg``: matplotlib
falls back to a non-interactive backend) nothing is drawn during the run; the buffers are
still filled and :meth:`LiveView.save` writes the last frame to an image file.
"""
from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from can_defs.frames import TICK_STEP_MS, CtrlMode
from controller.reference import ReferencePath, lateral_error
from hil.errors import HilError
from hil.metrics import CONTROL_PERIOD_MS, reference_path
from hil.run_types import HilRunResult, RunOptions
from hil.scenario import Scenario

#: Titles of the four panels, in order (the tests read them back from the figure).
PANEL_TITLES = ("Path and vehicle", "Lateral deviation e_Y",
                "Steering: ECU command and measured angle", "ECU mode and task time")

#: Samples kept per buffer: 10 min of virtual time at one sample per control cycle.
MAX_SAMPLES = 24_000


class LiveViewError(HilError):
    """The live view cannot be used as asked (an image format matplotlib does not write,
    an image that cannot be written)."""


def display_available() -> bool:
    """Whether matplotlib's backend is an interactive one (a window can open): False
    without a display, where matplotlib falls back to Agg, or with ``MPLBACKEND=Agg``."""
    import matplotlib
    from matplotlib.backends import BackendFilter, backend_registry

    return matplotlib.get_backend().lower() in backend_registry.list_builtin(BackendFilter.INTERACTIVE)


def image_formats() -> tuple[str, ...]:
    """File suffixes (without the dot) matplotlib writes: png, pdf, svg, ..."""
    from matplotlib.backend_bases import FigureCanvasBase

    return tuple(sorted(FigureCanvasBase.get_supported_filetypes()))


def check_image_path(path: Path, option: str = "--plot") -> None:
    """Refuse a file whose suffix is no format matplotlib writes (before the run).

    Raises:
        LiveViewError: names the option, the file and the formats.
    """
    suffix = path.suffix.lower().lstrip(".")
    formats = image_formats()
    if suffix not in formats:
        what = f"'.{suffix}' is not an image format" if suffix else "has no suffix"
        raise LiveViewError(f"{option} {path}: {what} (one of {', '.join(formats)})")


@dataclass
class LiveBuffers:
    """What the view shows, newest last; each a bounded deque (:data:`MAX_SAMPLES`).

    ``time``, ``x``, ``y``, ``yaw``, ``lateral_error``, ``steer``: the plant every sample
    period (s, m, m, rad, m, rad; the true pose, as ``hil.metrics`` measures e_Y, and the
    STEER_ANGLE the plant reports); ``cycle_time``, ``steer_cmd``, ``ctrl_mode``: each
    STEER_TORQUE_CMD received (s of its tick, rad, CtrlMode); ``task_time``, ``task_us``:
    each CTRL_DIAG received (s of its tick, CYCLE_TIME_US in us).
    """

    time: deque[float]
    x: deque[float]
    y: deque[float]
    yaw: deque[float]
    lateral_error: deque[float]
    steer: deque[float]
    cycle_time: deque[float]
    steer_cmd: deque[float]
    ctrl_mode: deque[int]
    task_time: deque[float]
    task_us: deque[float]

    @classmethod
    def empty(cls, max_samples: int = MAX_SAMPLES) -> "LiveBuffers":
        return cls(*(deque(maxlen=max_samples) for _ in range(11)))

    def array(self, name: str) -> np.ndarray:
        """One buffer as an array, shape (n,)."""
        return np.fromiter(getattr(self, name), dtype=float)


class LiveSampler:
    """The time master's ``on_tick``: samples the plant and the ECU frame monitor.

    Args:
        plant: the run's ``hil.plant_node.PlantNode`` (read: ``vehicle``).
        monitor: the run's ``hil.recorder.EcuFrameMonitor`` (read: ``commands``, ``diags``).
        path: the reference path e_Y is measured to.
        sample_period_ms: virtual time between plant samples (a multiple of the 5 ms tick;
            default one control cycle, at the control instants as ``hil.metrics``).
        max_samples: length of each buffer.
    """

    def __init__(self, plant: Any, monitor: Any, path: ReferencePath,
                 sample_period_ms: int = CONTROL_PERIOD_MS, max_samples: int = MAX_SAMPLES) -> None:
        if sample_period_ms <= 0 or sample_period_ms % TICK_STEP_MS:
            raise LiveViewError(f"sample period must be a positive multiple of {TICK_STEP_MS} ms, "
                                f"got {sample_period_ms}")
        self.plant, self.monitor, self.path = plant, monitor, path
        self.sample_period_ms = sample_period_ms
        self.buffers = LiveBuffers.empty(max_samples)
        self.samples = 0
        self._commands_seen = 0
        self._diags_seen = 0

    def __call__(self, tick_ms: int) -> bool:
        """After tick ``tick_ms``: take the ECU frames received since the last call, and
        the plant's state at ``tick_ms + 5`` ms when that is a sample instant. True when
        something new was taken."""
        new = self._take_ecu_frames()
        if (tick_ms + TICK_STEP_MS) % self.sample_period_ms:
            return new
        vehicle = self.plant.vehicle
        pose = vehicle.true_outputs()  # reads the state; the plant trace records the same
        foot = lateral_error(self.path, pose.x, pose.y, pose.yaw)
        b = self.buffers
        b.time.append((tick_ms + TICK_STEP_MS) / 1000.0)
        b.x.append(pose.x)
        b.y.append(pose.y)
        b.yaw.append(pose.yaw)
        b.lateral_error.append(foot.lateral_error)
        b.steer.append(vehicle.outputs().steer_angle)
        self.samples += 1
        return True

    def _take_ecu_frames(self) -> bool:
        commands, diags, b = self.monitor.commands, self.monitor.diags, self.buffers
        for tick, command in commands[self._commands_seen:]:
            b.cycle_time.append(tick / 1000.0)
            b.steer_cmd.append(command.steer_angle_cmd)
            b.ctrl_mode.append(int(command.ctrl_mode))
        for tick, diag in diags[self._diags_seen:]:
            b.task_time.append(tick / 1000.0)
            b.task_us.append(float(diag.cycle_time_us))
        new = len(commands) > self._commands_seen or len(diags) > self._diags_seen
        self._commands_seen, self._diags_seen = len(commands), len(diags)
        return new


class LiveFigure:
    """The four panels (module docstring) of one run, redrawn from :class:`LiveBuffers`.

    Args:
        path: the reference path (drawn once; the path panel zooms to the stretch driven).
        title: the figure's title (scenario, controller).
    """

    def __init__(self, path: ReferencePath, title: str = "") -> None:
        import matplotlib.pyplot as plt

        self.path = path
        self.title = title
        self.figure, axes = plt.subplots(2, 2, figsize=(12, 8), constrained_layout=True)
        self.path_axis, self.error_axis, self.steer_axis, self.mode_axis = axes.ravel()
        for axis, panel_title in zip(axes.ravel(), PANEL_TITLES):
            axis.set_title(panel_title)
            axis.grid(True, alpha=0.3)

        p = self.path_axis
        (self.reference_line,) = p.plot(path.x, path.y, "k--", linewidth=1, label="reference path")
        (self.trace_line,) = p.plot([], [], color="tab:blue", label="vehicle (true CG)")
        (self.pose_marker,) = p.plot([], [], marker="o", color="tab:red", linestyle="none",
                                     label="vehicle now")
        (self.heading_line,) = p.plot([], [], color="tab:red", linewidth=2)
        p.set_xlabel("X [m]")
        p.set_ylabel("Y [m]")
        p.legend(loc="upper left", fontsize="small")

        e = self.error_axis
        (self.error_line,) = e.plot([], [], color="tab:blue", label="e_Y (left of path +)")
        e.axhline(0.0, color="k", linewidth=0.8)
        e.set_xlabel("time [s]")
        e.set_ylabel("e_Y [m]")
        e.legend(loc="upper left", fontsize="small")

        s = self.steer_axis
        (self.steer_cmd_line,) = s.step([], [], where="post", color="tab:orange",
                                        label="STEER_ANGLE_CMD (ECU)")
        (self.steer_line,) = s.plot([], [], color="tab:blue", label="STEER_ANGLE (plant)")
        s.set_xlabel("time [s]")
        s.set_ylabel("front wheel angle [rad]")
        s.legend(loc="upper left", fontsize="small")

        m = self.mode_axis
        (self.mode_line,) = m.step([], [], where="post", color="tab:purple", label="CTRL_MODE")
        m.set_yticks([int(mode) for mode in CtrlMode], [mode.name for mode in CtrlMode])
        m.set_ylim(-0.5, max(CtrlMode) + 0.5)
        m.set_xlabel("time [s]")
        self.task_axis = m.twinx()
        (self.task_line,) = self.task_axis.plot([], [], color="tab:green", linewidth=0.8,
                                                label="task time (CYCLE_TIME_US)")
        self.task_axis.axhline(CONTROL_PERIOD_MS, color="tab:green", linestyle=":", linewidth=0.8,
                               label=f"control period {CONTROL_PERIOD_MS} ms")
        self.task_axis.set_ylabel("task time [ms]")
        handles = [self.mode_line, *self.task_axis.get_lines()]
        m.legend(handles, [h.get_label() for h in handles], loc="center right", fontsize="small")
        self.figure.suptitle(title)

    @property
    def panels(self) -> tuple[Any, ...]:
        """The four panels' axes, in :data:`PANEL_TITLES` order."""
        return self.path_axis, self.error_axis, self.steer_axis, self.mode_axis

    def update(self, buffers: LiveBuffers) -> None:
        """Set every line from ``buffers`` and rescale (draws nothing itself)."""
        t, x, y = buffers.array("time"), buffers.array("x"), buffers.array("y")
        self.trace_line.set_data(x, y)
        if t.size:
            yaw = buffers.yaw[-1]
            self.pose_marker.set_data([x[-1]], [y[-1]])
            self.heading_line.set_data([x[-1], x[-1] + 3.0 * np.cos(yaw)],
                                       [y[-1], y[-1] + 3.0 * np.sin(yaw)])
            self._zoom_path(x, y)
            self.figure.suptitle(f"{self.title}   t = {t[-1]:.2f} s")
        self.error_line.set_data(t, buffers.array("lateral_error"))
        self.steer_line.set_data(t, buffers.array("steer"))
        cycle_time = buffers.array("cycle_time")
        self.steer_cmd_line.set_data(cycle_time, buffers.array("steer_cmd"))
        self.mode_line.set_data(cycle_time, buffers.array("ctrl_mode"))
        self.task_line.set_data(buffers.array("task_time"), buffers.array("task_us") / 1000.0)
        for axis in (self.error_axis, self.steer_axis, self.task_axis):
            axis.relim()
            axis.autoscale_view()
        end = max([t[-1] if t.size else 0.0, cycle_time[-1] if cycle_time.size else 0.0, 0.1])
        for axis in (self.error_axis, self.steer_axis, self.mode_axis):
            axis.set_xlim(0.0, end)
        self.task_axis.set_ylim(bottom=0.0)

    def _zoom_path(self, x: np.ndarray, y: np.ndarray) -> None:
        """The stretch driven and 15 m ahead, with the reference's lateral extent there."""
        left, right = float(x.min()) - 5.0, float(x.max()) + 15.0
        near = (self.path.x >= left) & (self.path.x <= right)
        ys = np.concatenate([y, self.path.y[near]])
        low, high = float(ys.min()), float(ys.max())
        margin = max(1.0, 0.1 * (high - low))
        self.path_axis.set_xlim(left, right)
        self.path_axis.set_ylim(low - margin, high + margin)

    def draw(self, interactive: bool) -> None:
        """Render; in a window also let the GUI process its events (bounded, no wait)."""
        canvas = self.figure.canvas
        canvas.draw()
        # The layout engine costs about half of a redraw: lay out once, then keep the
        # panels where they are while the run goes (save lays out again).
        self.figure.set_layout_engine("none")
        if interactive:
            canvas.flush_events()

    def save(self, out: Path) -> Path:
        """Write the figure as it is now to ``out`` (format by suffix)."""
        self.figure.set_layout_engine("constrained")
        try:
            self.figure.savefig(out, dpi=100)
        except (OSError, ValueError) as error:
            raise LiveViewError(f"cannot write the live view {out}: {error}") from error
        return out

    def is_open(self) -> bool:
        """False once the window was closed by the user."""
        import matplotlib.pyplot as plt

        return plt.fignum_exists(self.figure.number)

    def close(self) -> None:
        import matplotlib.pyplot as plt

        plt.close(self.figure)


class LiveView:
    """Sampler and figure together: the ``on_tick`` of a run with a live view.

    Args:
        sampler: fills the buffers every tick.
        figure: draws them.
        interactive: a window is shown and redrawn during the run (else nothing is drawn
            until :meth:`save`).
        min_interval_s: the least wall-clock time between two redraws.
        draw_share: the most of the wall clock redraws may take (the interval grows to
            ``last redraw / draw_share``).
        clock: monotonic clock (s), injectable for tests.
    """

    def __init__(self, sampler: LiveSampler, figure: LiveFigure, *, interactive: bool,
                 min_interval_s: float = 0.1, draw_share: float = 0.2,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.sampler, self.figure, self.interactive = sampler, figure, interactive
        self.min_interval_s, self.draw_share, self.clock = min_interval_s, draw_share, clock
        self.redraws = 0
        self.draw_time_s = 0.0
        self._interval_s = min_interval_s
        self._next_draw = clock()
        self._stale = False

    @property
    def buffers(self) -> LiveBuffers:
        return self.sampler.buffers

    def on_tick(self, tick_ms: int) -> None:
        """Sample; redraw when the window is shown and the interval has passed."""
        self._stale |= self.sampler(tick_ms)
        if not self.interactive or not self._stale or self.clock() < self._next_draw:
            return
        if not self.figure.is_open():  # closed by the user: the run goes on without it
            self.interactive = False
            return
        self.redraw()

    def redraw(self) -> None:
        """Update the lines and render now; schedules the next redraw."""
        started = self.clock()
        self.figure.update(self.sampler.buffers)
        self.figure.draw(self.interactive)
        spent = self.clock() - started
        self.redraws += 1
        self.draw_time_s += spent
        self._stale = False
        self._interval_s = max(self.min_interval_s, spent / self.draw_share)
        self._next_draw = started + self._interval_s

    def save(self, out: Path) -> Path:
        """The last frame (every sample taken) to ``out``."""
        self.figure.update(self.sampler.buffers)
        return self.figure.save(out)

    def hold(self) -> None:
        """Show the final frame until the user closes the window (interactive only)."""
        if not self.interactive or not self.figure.is_open():
            return
        import matplotlib.pyplot as plt

        self.redraw()
        plt.ioff()
        plt.show(block=True)

    def close(self) -> None:
        self.figure.close()


def open_live_view(rig: Any, interactive: bool, **options: Any) -> LiveView:
    """A live view of ``rig`` (``hil.rig.Rig``, built, not necessarily started): its
    plant, its monitor and its scenario's path; a window when ``interactive``."""
    import matplotlib.pyplot as plt

    if interactive:
        plt.ion()
    path = reference_path(rig.scenario)
    sampler = LiveSampler(rig.plant, rig.monitor, path)
    figure = LiveFigure(path, title=f"{rig.scenario.name} - {rig.options.controller}")
    if interactive:
        figure.figure.show()
    return LiveView(sampler, figure, interactive=interactive, **options)


def run_with_live_view(scenario: Scenario, options: RunOptions, interactive: bool,
                       **view_options: Any) -> tuple[HilRunResult, LiveView]:
    """``hil.session.run_hil`` with a :class:`LiveView` as the time master's ``on_tick``
    (its buffers full at the end; the caller saves, holds or closes it)."""
    from hil.rig import Rig

    rig = Rig(scenario, options)
    view = open_live_view(rig, interactive, **view_options)
    try:
        with rig:
            rig.run(on_tick=view.on_tick)
    except BaseException:
        view.close()
        raise
    return rig.result(), view
