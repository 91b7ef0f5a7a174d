"""Decoded signals of a recorded CAN log: a CSV table and an overview plot.

CSV layout (decided: one row per frame, lossless): every frame of the log in file order
with its time (`hil.logio.frame_times`: virtual time in lockstep logs, else timestamps
relative to the first frame), the raw timestamp, ID, frame name, alive counter, the E2E
verdict of a receiver that saw the whole log (``can_defs.E2EMonitor``: ok, crc_error,
repeated, lost, sequence_error, wrong_length, unknown_id, bad_tick) and one column per
signal (snake case), empty where the frame does not carry it. Frames outside the DBC keep
their ID and raw payload (``data``) with ``e2e`` = unknown_id.

The plot draws each signal at the frames that carry it (commands as steps): speed (VX, TARGET_SPEED),
steering (STEER_ANGLE_CMD against the measured STEER_ANGLE), yaw rate, the path driven
(POS_X, POS_Y) against the reference path, and the lateral deviation e_Y from it
(`hil.metrics.path_errors`) over time.
"""
from __future__ import annotations

import csv
import dataclasses
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import numpy as np

from can_defs.codec import decode
from can_defs.e2e import E2EMonitor
from can_defs.errors import CanDefsError
from can_defs.frames import FRAME_CLASSES, FrameId
from hil.errors import HilError
from hil.logio import LogContents, frame_times, is_contract_data_frame

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

    def series(self, signal: str, frame_id: FrameId | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(time (n,), value (n,)) of one signal over the frames that carry it and whose
        E2E verdict accepted them (ok / lost, or a HIL frame)."""
        times, values = [], []
        for row in self.rows:
            if signal in row and row["e2e"] in ("ok", "lost") and (
                    frame_id is None or row["id"] == int(frame_id)):
                times.append(row["time_s"])
                values.append(float(row[signal]))
        return np.asarray(times, dtype=float), np.asarray(values, dtype=float)


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
            kind = ("error" if message.is_error_frame else "remote" if message.is_remote_frame
                    else "extended")
            row.update(frame=f"({kind} frame)", e2e="unknown_id")
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


def write_csv(decoded: DecodedLog, path: str | Path) -> Path:
    """Write the one-row-per-frame table (module docstring)."""
    path = Path(path)
    columns = FRAME_COLUMNS + SIGNAL_COLUMNS
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
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
    """Overview figure (module docstring) to ``out`` (PNG, or any matplotlib format).

    Args:
        decoded: the decoded log.
        path: reference path (`ReferencePath`) for the path panel and e_Y; None skips both.
        out: image file.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    figure, axes = plt.subplots(5, 1, figsize=(9, 13), constrained_layout=True)
    speed, steer, yaw_rate, xy, lateral = axes

    t_vx, vx = decoded.series("vx", FrameId.VEH_DYN)
    t_target, target = decoded.series("target_speed", FrameId.PLANNER_REQ)
    speed.plot(t_vx, vx, label="VX (measured)")
    if t_target.size:
        speed.step(t_target, target, where="post", label="TARGET_SPEED (planner)", linestyle="--")
    speed.set_ylabel("speed [m/s]")

    t_cmd, steer_cmd = decoded.series("steer_angle_cmd", FrameId.STEER_TORQUE_CMD)
    t_meas, steer_meas = decoded.series("steer_angle", FrameId.VEH_POSE_YAW)
    steer.plot(t_meas, steer_meas, label="STEER_ANGLE (measured)")
    if t_cmd.size:
        steer.step(t_cmd, steer_cmd, where="post", label="STEER_ANGLE_CMD (ECU)", linestyle="--")
    steer.set_ylabel("front wheel angle [rad]")

    t_r, r = decoded.series("yaw_rate", FrameId.VEH_DYN)
    yaw_rate.plot(t_r, r, label="YAW_RATE")
    yaw_rate.set_ylabel("yaw rate [rad/s]")
    yaw_rate.set_xlabel(f"time [s] ({decoded.time_base})")

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

    if path is not None and t_xy.size:
        t_e, e_y = lateral_deviation(decoded, path)
        lateral.plot(t_e, e_y, label="e_Y")
        lateral.set_title(f"e_Y: max |e_Y| {np.max(np.abs(e_y)):.4f} m")
    else:
        lateral.text(0.5, 0.5, "no reference path or no pose frames", ha="center",
                     transform=lateral.transAxes)
    lateral.set_ylabel("e_Y [m] (left +)")
    lateral.set_xlabel(f"time [s] ({decoded.time_base})")
    for axis in axes:
        axis.grid(True, alpha=0.3)
        if axis.get_legend_handles_labels()[0]:
            axis.legend(loc="best", fontsize="small")
    if title:
        figure.suptitle(title)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
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
