"""Decoded signals of a recorded CAN log: a CSV table and an overview plot.

CSV layout (decided: one row per frame, lossless): every frame of the log in file order
with its time (`hil.logio.frame_times`: virtual time in lockstep logs, else timestamps
relative to the first frame), the raw timestamp, ID, frame name, alive counter, the E2E
verdict of a receiver that saw the whole log (``can_defs.E2EMonitor``: ok, crc_error,
repeated, lost, sequence_error, wrong_length, unknown_id, bad_tick) and one column per
signal (snake case), empty where the frame does not carry it. Frames outside the DBC keep
their ID and raw payload (``data``) with ``e2e`` = unknown_id; a frame the contract never
uses is named by its kind (`non_contract_label`: CAN FD, remote, error, extended).

The plot draws each signal at the frames that carry it (commands as steps): speed (VX, TARGET_SPEED),
steering (STEER_ANGLE_CMD against the measured STEER_ANGLE), yaw rate, the path driven
(POS_X, POS_Y) against the reference path, and the lateral deviation e_Y from it
(`hil.metrics.path_errors`) over time.

Another DBC (``--dbc FILE``, `load_display_dbc`): a foreign log is decoded with its own
DBC through cantools (`decode_with_dbc`): the same leading columns (without the contract's
alive counter and E2E verdict), then one column per signal, ``MESSAGE.SIGNAL``; its plot
(`plot_signals`) has one panel per message, a line per signal with its unit. The DBC only
changes how a log is read and shown, never what an ECU uses.

Nothing to plot (a foreign log read with the contract's DBC, or a DBC none of whose
messages are in the log): `nothing_to_plot` says why, and the command warns instead of
writing an empty figure.
"""
from __future__ import annotations

import csv
import dataclasses
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import can
import numpy as np

from can_defs.codec import decode
from can_defs.dbc import DBC_PATH
from can_defs.e2e import E2EMonitor
from can_defs.errors import CanDefsError
from can_defs.frames import FRAME_CLASSES, FrameId
from can_defs.log_reader import FrameKind, frame_kind
from hil.errors import HilError
from hil.logio import LogContents, dbc_message, frame_times, is_contract_data_frame

#: Signal columns in table order: every field of every contract frame, once.
SIGNAL_COLUMNS: tuple[str, ...] = tuple(dict.fromkeys(
    f.name for cls in FRAME_CLASSES.values() for f in dataclasses.fields(cls)))

#: Leading columns of the CSV.
FRAME_COLUMNS: tuple[str, ...] = ("time_s", "timestamp", "id", "frame", "counter", "e2e", "data")


class DecodeLogError(HilError):
    """The decoded log cannot be written or plotted (the message says why)."""


@dataclass
class DecodedLog:
    """One row per frame (column -> value; missing signals absent) plus counts."""

    time_base: str
    rows: list[dict[str, Any]]
    e2e_counts: dict[str, int] = field(default_factory=dict)
    undecodable: int = 0
    #: CSV columns in order (the contract's by default).
    columns: tuple[str, ...] = FRAME_COLUMNS + SIGNAL_COLUMNS
    #: Another DBC's signals: column -> (message name, signal name, unit); empty for the
    #: contract's DBC.
    dbc_signals: dict[str, tuple[str, str, str]] = field(default_factory=dict)

    def series(self, signal: str, frame_id: FrameId | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(time (n,), value (n,)) of one signal over the frames that carry it and whose
        E2E verdict accepted them (ok / lost, or a HIL frame)."""
        times, values = [], []
        for row in self.rows:
            if signal in row and row.get("e2e", "ok") in ("ok", "lost") and (
                    frame_id is None or row["id"] == int(frame_id)):
                times.append(row["time_s"])
                values.append(float(row[signal]))
        return np.asarray(times, dtype=float), np.asarray(values, dtype=float)


#: The word `non_contract_label` gives each frame kind (a classic data frame has none).
_KIND_WORDS: dict[FrameKind, str] = {FrameKind.DATA: "", FrameKind.FD: "CAN FD",
                                     FrameKind.REMOTE: "remote", FrameKind.ERROR: "error"}


def non_contract_label(message: can.Message) -> str:
    """The ``frame`` cell of a frame that is no contract frame, named by `frame_kind` (the
    one test of what a frame is) and its ID length: "(CAN FD frame)", "(extended CAN FD
    frame)", "(remote frame)", "(extended remote frame)", "(extended frame)" or "(error
    frame)" (an error frame's ID flag means nothing, so it is never called extended)."""
    kind = frame_kind(message)
    extended = "extended" if message.is_extended_id and kind is not FrameKind.ERROR else ""
    return "(" + " ".join(word for word in (extended, _KIND_WORDS[kind], "frame") if word) + ")"


def decode_log(contents: LogContents) -> DecodedLog:
    """Decode every frame of a log (see the module docstring for the columns)."""
    times, time_base = frame_times(contents.messages)
    monitor = E2EMonitor()
    rows: list[dict[str, Any]] = []
    undecodable = 0
    for message, time_s in zip(contents.messages, times):
        row: dict[str, Any] = {"time_s": time_s, "timestamp": message.timestamp,
                               "id": message.arbitration_id, "data": bytes(message.data or b"").hex()}
        if not is_contract_data_frame(message):
            row.update(frame=non_contract_label(message), e2e="unknown_id")
            rows.append(row)
            continue
        result = monitor.check(message.arbitration_id, bytes(message.data))
        row["e2e"] = result.status.value
        try:
            row["frame"] = FrameId(message.arbitration_id).name
        except ValueError:
            row["frame"] = "(not in DBC)"
            rows.append(row)
            continue
        try:
            decoded = decode(message.arbitration_id, bytes(message.data))
        except CanDefsError:
            undecodable += 1
            rows.append(row)
            continue
        if decoded.counter is not None:
            row["counter"] = decoded.counter
        for item in dataclasses.fields(decoded.frame):
            value = getattr(decoded.frame, item.name)
            row[item.name] = int(value) if isinstance(value, (bool, IntEnum)) else value
        rows.append(row)
    counts = {status.value: n for status, n in monitor.stats.counts.items() if n}
    return DecodedLog(time_base=time_base, rows=rows, e2e_counts=counts, undecodable=undecodable)


def load_display_dbc(path: str | Path | None) -> Any:
    """The cantools database of ``--dbc FILE``; None for the contract's own DBC (``None``
    or ``can_defs/vehicle.dbc``), which `decode_log` reads with the project's codec.

    Any format cantools reads (.dbc, .kcd, .sym, .arxml), loaded without the strict
    overlap checks the contract's DBC gets: a foreign file is read as its authors wrote it.

    Raises:
        DecodeLogError: the file is missing or not a CAN database.
    """
    if path is None:
        return None
    path = Path(path)
    try:
        if path.resolve() == DBC_PATH.resolve():
            return None
    except OSError:
        pass
    import cantools

    if not path.is_file():
        raise DecodeLogError(f"--dbc {path}: no such file")
    try:
        database = cantools.database.load_file(str(path), strict=False)
    except Exception as error:  # noqa: BLE001 - cantools' parsers raise many kinds
        raise DecodeLogError(f"--dbc {path}: not a readable CAN database: "
                             f"{type(error).__name__}: {error}") from error
    if not isinstance(database, cantools.database.can.Database) or not database.messages:
        raise DecodeLogError(f"--dbc {path}: holds no CAN message")
    return database


def decode_with_dbc(contents: LogContents, database: Any) -> DecodedLog:
    """Decode every frame of a log with another DBC (module docstring): one row per
    frame; signals as numbers (choices as their raw values), ``MESSAGE.SIGNAL`` columns."""
    times, time_base = frame_times(contents.messages)
    signals: dict[str, tuple[str, str, str]] = {}
    for db_message in database.messages:
        for signal in db_message.signals:
            signals[f"{db_message.name}.{signal.name}"] = (db_message.name, signal.name,
                                                           signal.unit or "")
    rows: list[dict[str, Any]] = []
    undecodable = 0
    for message, time_s in zip(contents.messages, times):
        row: dict[str, Any] = {"time_s": time_s, "timestamp": message.timestamp,
                               "id": message.arbitration_id, "data": bytes(message.data or b"").hex()}
        rows.append(row)
        db_message = dbc_message(database, message)
        if frame_kind(message) in (FrameKind.ERROR, FrameKind.REMOTE):
            row["frame"] = (f"{db_message.name} (remote)" if db_message is not None
                            else non_contract_label(message))
            continue
        if db_message is None:
            row["frame"] = "(not in DBC)"
            continue
        row["frame"] = db_message.name
        try:
            values = db_message.decode(bytes(message.data), decode_choices=False,
                                       allow_truncated=True)
        except Exception:  # noqa: BLE001 - a foreign payload may not fit its message
            undecodable += 1
            continue
        for name, value in values.items():
            if isinstance(value, (int, float)):
                row[f"{db_message.name}.{name}"] = value
    leading = tuple(c for c in FRAME_COLUMNS if c not in ("counter", "e2e"))
    return DecodedLog(time_base=time_base, rows=rows, undecodable=undecodable,
                      columns=leading + tuple(signals), dbc_signals=signals)


#: Signals of the contract's overview plot; without any of them there is nothing to plot.
_OVERVIEW_SIGNALS: tuple[tuple[str, FrameId], ...] = (
    ("vx", FrameId.VEH_DYN), ("steer_angle", FrameId.VEH_POSE_YAW),
    ("pos_x", FrameId.VEH_POSE_XY), ("steer_angle_cmd", FrameId.STEER_TORQUE_CMD))


def nothing_to_plot(decoded: DecodedLog) -> str | None:
    """Why a plot of ``decoded`` would be empty, None when it has something to show."""
    if decoded.dbc_signals:
        if any(column in row for row in decoded.rows for column in decoded.dbc_signals):
            return None
        return "no frame of the log decodes to a signal of this DBC"
    if any(decoded.series(signal, frame_id)[0].size for signal, frame_id in _OVERVIEW_SIGNALS):
        return None
    return ("the log holds no accepted VEH_DYN, VEH_POSE_XY, VEH_POSE_YAW or STEER_TORQUE_CMD "
            "frame of the contract (a foreign log? decode it with its own DBC: --dbc FILE)")


def write_csv(decoded: DecodedLog, path: str | Path) -> Path:
    """Write the one-row-per-frame table (module docstring)."""
    path = Path(path)
    columns = decoded.columns
    try:
        with path.open("w", newline="", encoding="ascii") as handle:
            writer = csv.writer(handle)
            writer.writerow(columns)
            for row in decoded.rows:
                writer.writerow([_cell(column, row.get(column)) for column in columns])
    except OSError as error:
        raise DecodeLogError(f"cannot write {path}: {error}") from error
    return path


def _cell(column: str, value: Any) -> str:
    if value is None:
        return ""
    if column == "id":
        return f"0x{value:03X}"
    if column == "timestamp":
        return f"{value:.6f}"
    if isinstance(value, float):
        return f"{value:.9g}"
    return str(value)


def lateral_deviation(decoded: DecodedLog, path: Any) -> tuple[np.ndarray, np.ndarray]:
    """(time (n,), e_Y (n,)) at every accepted VEH_POSE_XY frame, against ``path``
    (`controller.reference.ReferencePath`); e_Y does not depend on the heading."""
    from hil.metrics import path_errors

    times, x = decoded.series("pos_x", FrameId.VEH_POSE_XY)
    _, y = decoded.series("pos_y", FrameId.VEH_POSE_XY)
    if times.size == 0:
        return times, times
    pose = np.column_stack([x, y, np.zeros_like(x)])
    return times, path_errors(pose, path).lateral_error


def plot_log(decoded: DecodedLog, path: Any, out: str | Path, title: str = "") -> Path:
    """Overview figure (`overview_figure`) to ``out`` (PNG, or any matplotlib format).

    Args:
        decoded: the decoded log.
        path: reference path (`ReferencePath`) for the path panel and e_Y; None skips both.
        out: image file.
    """
    return _save(overview_figure(decoded, path, title), out)


def overview_figure(decoded: DecodedLog, path: Any, title: str = "") -> Any:
    """The overview (module docstring) as a matplotlib figure: five titled panels with
    units on both axes and a legend for every line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(5, 1, figsize=(9, 13), constrained_layout=True)
    speed, steer, yaw_rate, xy, lateral = axes

    t_vx, vx = decoded.series("vx", FrameId.VEH_DYN)
    t_target, target = decoded.series("target_speed", FrameId.PLANNER_REQ)
    speed.plot(t_vx, vx, label="VX (measured)")
    if t_target.size:
        speed.step(t_target, target, where="post", label="TARGET_SPEED (planner)", linestyle="--")
    speed.set_ylabel("speed [m/s]")
    speed.set_title("Longitudinal speed: measured and requested")

    t_cmd, steer_cmd = decoded.series("steer_angle_cmd", FrameId.STEER_TORQUE_CMD)
    t_meas, steer_meas = decoded.series("steer_angle", FrameId.VEH_POSE_YAW)
    steer.plot(t_meas, steer_meas, label="STEER_ANGLE (measured)")
    if t_cmd.size:
        steer.step(t_cmd, steer_cmd, where="post", label="STEER_ANGLE_CMD (ECU)", linestyle="--")
    steer.set_ylabel("front wheel angle [rad]")
    steer.set_title("Steering: ECU command and measured angle")

    t_r, r = decoded.series("yaw_rate", FrameId.VEH_DYN)
    yaw_rate.plot(t_r, r, label="YAW_RATE")
    yaw_rate.set_ylabel("yaw rate [rad/s]")
    yaw_rate.set_title("Yaw rate (measured)")
    for axis in (speed, steer, yaw_rate):
        axis.set_xlabel(f"time [s] ({decoded.time_base})")

    t_xy, x = decoded.series("pos_x", FrameId.VEH_POSE_XY)
    _, y = decoded.series("pos_y", FrameId.VEH_POSE_XY)
    if path is not None and t_xy.size:
        # The reference over the stretch driven (plus a margin), not the whole path.
        margin = 5.0
        shown = (path.x >= x.min() - margin) & (path.x <= x.max() + margin)
        xy.plot(path.x[shown], path.y[shown], color="grey", linestyle="--", label="reference")
    xy.plot(x, y, label="driven (POS_X, POS_Y)")
    xy.set_xlabel("X [m]")
    xy.set_ylabel("Y [m]")
    xy.set_title("Path driven against the reference path")

    if path is not None and t_xy.size:
        t_e, e_y = lateral_deviation(decoded, path)
        lateral.plot(t_e, e_y, label="e_Y (at each accepted VEH_POSE_XY)")
        lateral.set_title(f"Lateral deviation e_Y from the reference: max |e_Y| "
                          f"{np.max(np.abs(e_y)):.4f} m")
    else:
        lateral.set_title("Lateral deviation e_Y from the reference")
        lateral.text(0.5, 0.5, "no reference path or no pose frames", ha="center",
                     transform=lateral.transAxes)
    lateral.set_ylabel("e_Y [m] (left +)")
    lateral.set_xlabel(f"time [s] ({decoded.time_base})")
    for axis in axes:
        axis.grid(True, alpha=0.3)
        if axis.get_legend_handles_labels()[0]:
            axis.legend(loc="best", fontsize="small")
    figure.suptitle(title or "CAN log overview")
    return figure


#: At most this many panels (messages) in `plot_signals`; the most frequent are shown.
MAX_SIGNAL_PANELS = 8
#: At most this many signals (lines) per panel.
MAX_SIGNALS_PER_PANEL = 8


def plot_signals(decoded: DecodedLog, out: str | Path, title: str) -> Path:
    """`signals_figure` to ``out``.

    Raises:
        DecodeLogError: nothing to plot (`nothing_to_plot`) or the file cannot be written.
    """
    return _save(signals_figure(decoded, title), out)


def signals_figure(decoded: DecodedLog, title: str) -> Any:
    """Figure of a log decoded with another DBC: one panel per message (the
    :data:`MAX_SIGNAL_PANELS` most frequent), a line per signal labelled with its unit.

    Raises:
        DecodeLogError: nothing to plot (`nothing_to_plot`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    problem = nothing_to_plot(decoded)
    if problem is not None:
        raise DecodeLogError(f"nothing to plot: {problem}")
    per_message: dict[str, dict[str, tuple[list[float], list[float]]]] = {}
    for row in decoded.rows:
        for column, (message, signal, _) in decoded.dbc_signals.items():
            if column in row:
                times, values = per_message.setdefault(message, {}).setdefault(signal, ([], []))
                times.append(row["time_s"])
                values.append(float(row[column]))
    ranked = sorted(per_message, key=lambda m: -max(len(t) for t, _ in per_message[m].values()))
    shown = ranked[:MAX_SIGNAL_PANELS]
    units = {(m, sig): unit for m, sig, unit in decoded.dbc_signals.values()}
    figure, axes = plt.subplots(len(shown), 1, figsize=(9, 2.6 * len(shown) + 0.6),
                                constrained_layout=True, squeeze=False)
    for axis, message in zip(axes[:, 0], shown):
        signals = list(per_message[message].items())
        for signal, (times, values) in signals[:MAX_SIGNALS_PER_PANEL]:
            unit = units.get((message, signal)) or "no unit"
            axis.plot(times, values, label=f"{signal} [{unit}]")
        more = len(signals) - MAX_SIGNALS_PER_PANEL
        axis.set_title(message + (f" ({more} more signals in the CSV)" if more > 0 else ""))
        axis.set_ylabel("value [unit in legend]")
        axis.set_xlabel(f"time [s] ({decoded.time_base})")
        axis.grid(True, alpha=0.3)
        axis.legend(loc="best", fontsize="small")
    left_out = len(ranked) - len(shown)
    figure.suptitle(title + (f"; {left_out} less frequent messages only in the CSV"
                             if left_out > 0 else ""))
    return figure


def _save(figure: Any, out: str | Path) -> Path:
    """Write and close a figure; `DecodeLogError` when the file cannot be written."""
    import matplotlib.pyplot as plt

    out = Path(out)
    try:
        figure.savefig(out, dpi=110)
    except (OSError, ValueError) as error:
        raise DecodeLogError(f"cannot write the plot {out}: {error}") from error
    finally:
        plt.close(figure)
    return out


def most_requested_path_id(decoded: DecodedLog) -> int | None:
    """The PATH_ID the planner requested most often, None without PLANNER_REQ."""
    _, ids = decoded.series("path_id", FrameId.PLANNER_REQ)
    if ids.size == 0:
        return None
    values, counts = np.unique(ids.astype(int), return_counts=True)
    return int(values[np.argmax(counts)])
