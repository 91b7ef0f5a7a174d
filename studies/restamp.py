"""Restamp results after a change that keeps behaviour, on the proof of a smoke subset.

A refactor or a speed-up of the product code changes the sources that
``results/PROVENANCE.json`` records for every study, so each study's files go stale although
none of their figures can move. This command checks that claim and, when it holds, moves
the stamps to the current commit instead of rerunning hours of studies:

    python -m studies.restamp --base REV [--dry-run] [--workdir build/restamp]

1. **Candidates.** Every stamped results file that ``python -m studies.provenance check``
   finds stale because its inputs changed (not because the file itself changed), whose stamp
   was current at ``REV`` (its inputs and sources as committed at ``REV`` give the recorded
   digest), where every file that changed since then is code the smoke runs (the Python
   modules that ``eso-hil run`` and ``eso-ecu`` import, the fault injection and studies/
   left out, and the C ECU's firmware/src; :func:`smoke_sources`) or code the training
   smoke runs (the trainer and the data generator, ``studies.restamp_training``), and whose
   command does not measure the machine or the build (``make timing``, ``make bench``,
   ``make can-bench``, ``make firmware-footprint``: their figures are what a code change
   moves). A changed data file (tuning, artefact, scenario, path, DBC) or study module
   always needs the rerun.
2. **The smoke subset** of the closed-loop studies, run at ``REV`` (a git worktree under
   ``--workdir``, its C ECU built there) and on this checkout: a lockstep run over CAN
   (``eso-hil run``) of every controller of the Python ECU and of the C ECU under the
   shipped tuning, on ``dlc_smoke`` and on the same lane change under a steering offset, a
   crosswind and a yaw-rate bias (:data:`DISTURBED_SMOKE`).
   When a candidate's changes reach the trainer's own code, the training smoke runs too
   (``studies.restamp_training``): a small data set generated and short trainings of the
   default form and of a least-squares lift, in both trees; their artefacts must be equal,
   array for array, byte for byte.
3. **The check.** Each frame log must equal its twin frame for frame: identifier, payload and
   time since the first frame (to 0.1 ms: the stamps carry the wall-clock start; not for
   HIL_SYNC_ACK, whose stamp races the next tick and whose payload names its tick), with CTRL_DIAG's wall-clock signals (SOLVE_TIME_US,
   CYCLE_TIME_US, OVERRUNS and the CRC over them) left out. One difference anywhere and
   nothing is restamped (exit 1, the first differing frame named).
4. **Restamp.** Each candidate's stamp gets this checkout's sources and commit, its output
   digest unchanged (the file is not rewritten), and a ``restamped`` record naming ``REV``
   and this command. A ``results/KNOWN_STALE.md`` row whose files are all restamped goes.

The smoke runs the shipped settings: a study that runs other settings (the tuning sweeps,
the trade-off, the observer variants) is covered where those settings take the same code
paths. Where a change reaches a path that only such settings take (a training option off in
the default form, say), ``--exclude GLOB`` (repeatable, matched against the results path)
leaves those files stale: they need their rerun, or a row in results/KNOWN_STALE.md. Exit status: 0 restamped (or nothing to do), 1 the smoke differs, 2 bad input.
"""
from __future__ import annotations

import argparse
import fnmatch
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cantools

from can_defs.log_reader import LogFileError, read_log_frames
from studies import provenance
from studies.restamp_training import (TrainingSmokeError, artefact_difference, default_form, training_smoke,
                                      training_sources)

#: The entry points of the smoke runs: ``eso-hil run`` and the Python ECU's command line.
SMOKE_ENTRY_MODULES = ("hil.commands.run", "firmware_sim.__main__")
#: Code those entry points import that the smoke does not execute: the fault injection
#: (the smoke runs inject no fault), so a change there needs the fault studies' reruns.
NOT_EXERCISED = re.compile(r"hil/fault[^/]*\.py|hil/fault_cases/.*")
#: Commands whose files measure the machine or the build: a code change is what they measure.
MACHINE_COMMANDS = ("make timing", "make bench", "make can-bench", "make firmware-footprint")
#: The controllers of each ECU (``eso-hil run --ecu``).
SMOKE_CONTROLLERS = {
    "python": ("eso-dkmpc", "dkmpc", "lmpc", "nmpc", "lmpc-eso", "dmdc-eso", "stanley"),
    "c": ("eso-dkmpc", "dkmpc", "lmpc"),
}
#: dlc_smoke with a constant disturbance of each kind the observer is for (docs/plant.md).
DISTURBED_SMOKE = """name = "dlc_smoke_disturbed"
description = "dlc_smoke under a steering offset, a crosswind and a yaw-rate bias (restamp smoke)"
duration_s = 4.0

[path]
id = 1
file = "{path}"

[road]
mu = 0.85

[start]
x_m = 10.0
y_m = 0.0135
yaw_rad = 0.0026
speed_kmh = 35.0

[speed_profile]
time_s = [0.0]
target_speed_kmh = [35.0]

[disturbances]
steer_offset_rad = 0.01
crosswind_force_n = 400.0
yaw_rate_bias_rad_s = 0.005
"""
#: CTRL_DIAG's signals that the host's clock decides, not the control law.
WALL_CLOCK_SIGNALS = {"CTRL_DIAG": ("CRC", "SOLVE_TIME_US", "CYCLE_TIME_US", "OVERRUNS")}
#: Frames whose log stamp races the time master's next tick (the ECU's acknowledgement of a
#: tick is logged at that tick or the next one); their payload names the tick.
UNTIMED_FRAMES = ("HIL_SYNC_ACK",)
RUN_TIMEOUT_S = 600
#: Frame times are compared to 0.1 ms (a lockstep tick is 1 ms).
TIME_RESOLUTION_US = 100


class RestampError(Exception):
    """The check cannot run (no such revision, a smoke run failed, a log missing)."""


@dataclass(frozen=True)
class Candidate:
    """A stale results file that a behaviour-keeping change may restamp."""

    path: str
    command: str
    changed: tuple[str, ...]
    #: the combined digest of its inputs and sources here when it was chosen
    digest: str = ""


# ---------------------------------------------------------------------------- candidates

def smoke_sources(root: Path = provenance.ROOT) -> frozenset[str]:
    """The source files (paths from ``root``) that the smoke runs execute: the project
    modules ``eso-hil run`` and ``eso-ecu`` import, transitively, without the fault
    injection (:data:`NOT_EXERCISED`) and studies/ (a study's code is not what its smoke
    runs), and the C ECU's sources."""
    modules = provenance.module_sources(SMOKE_ENTRY_MODULES, root)
    python = {name for name in (path.relative_to(root).as_posix() for path in modules)
              if not NOT_EXERCISED.fullmatch(name)}
    firmware = {path.relative_to(root).as_posix() for path in (root / "firmware" / "src").glob("*.[ch]")}
    return frozenset({name for name in python if not name.startswith("studies/")} | firmware)


def candidates(base_root: Path, root: Path = provenance.ROOT,
               covered: frozenset[str] | None = None) -> tuple[list[Candidate], dict[str, str]]:
    """The stale results files of ``root`` that a check against the tree ``base_root`` (the
    base revision's checkout) may restamp, and the others with the reason for each;
    ``covered``: the files the smoke runs (default :func:`smoke_sources` of ``root``)."""
    manifest = provenance.load_manifest(root)
    covered = smoke_sources(root) | training_sources(root) if covered is None else covered
    eligible: list[Candidate] = []
    refused: dict[str, str] = {}
    for entry in provenance.check(root):
        stamp = manifest.get(entry.path)
        if stamp is None or any(not r.startswith("inputs changed") for r in entry.reasons):
            refused[entry.path] = "; ".join(entry.reasons)
            continue
        if stamp["command"].startswith(MACHINE_COMMANDS):
            refused[entry.path] = f"`{stamp['command']}` measures the machine or the build: rerun it"
            continue
        try:
            at_base = provenance.input_digests(stamp["inputs"], stamp["modules"], base_root)
        except provenance.ProvenanceError as exc:
            refused[entry.path] = f"cannot be traced at the base revision: {exc}"
            continue
        if provenance.combined_digest(at_base) != stamp["sha256"]:
            refused[entry.path] = "its stamp was not current at the base revision"
            continue
        now = provenance.input_digests(stamp["inputs"], stamp["modules"], root)
        changed = tuple(sorted(name for name in set(now) | set(at_base)
                               if now.get(name) != at_base.get(name)))
        other = [name for name in changed if name not in covered]
        if other:
            refused[entry.path] = f"changed beyond the code the smoke runs: {', '.join(other[:4])}: rerun it"
            continue
        eligible.append(Candidate(entry.path, stamp["command"], changed, provenance.combined_digest(now)))
    return eligible, refused


def excluded_candidates(chosen: list[Candidate], patterns: list[str]) -> tuple[list[Candidate], list[Candidate]]:
    """``chosen`` split into those no pattern of ``patterns`` (fnmatch globs on the results
    path) matches and those one does (left stale)."""
    left = [c for c in chosen if any(fnmatch.fnmatch(c.path, pattern) for pattern in patterns)]
    return [c for c in chosen if c not in left], left


# ---------------------------------------------------------------------------- smoke

def base_checkout(revision: str, workdir: Path, root: Path = provenance.ROOT) -> Path:
    """A detached git worktree of ``revision`` at ``workdir``/base, sharing this checkout's
    virtual environment, with its C ECU built. Raises RestampError for an unknown revision."""
    resolved = subprocess.run(["git", "rev-parse", "--verify", f"{revision}^{{commit}}"], cwd=root,
                              capture_output=True, text=True)
    if resolved.returncode != 0:
        raise RestampError(f"--base {revision}: not a commit of this repository")
    base = workdir / "base"
    if base.exists():
        subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=root, capture_output=True)
        shutil.rmtree(base, ignore_errors=True)
    subprocess.run(["git", "worktree", "prune"], cwd=root, check=True, capture_output=True)
    subprocess.run(["git", "worktree", "add", "--detach", str(base), resolved.stdout.strip()],
                   cwd=root, check=True, capture_output=True)
    link = base / ".venv"
    if link.is_symlink():  # a revision that tracked a .venv link: point it at this environment
        link.unlink()
    link.symlink_to((root / ".venv").resolve())
    build_firmware(base)
    return base


def build_firmware(tree: Path) -> None:
    """``make firmware`` in ``tree`` (the C ECU of the smoke runs). The environment's install
    stamp counts as up to date (``make -o``): a worktree's fresh pyproject.toml must not
    reinstall the shared virtual environment as an editable install of the worktree. The
    generators import ``tree``'s own packages (``PYTHONPATH``, as the smoke runs do): the
    shared environment's editable install points at the checkout, whose tuning loader may
    want fields the base's tuning file does not have."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    done = subprocess.run(["make", "--no-print-directory", "-o", ".venv/.installed", "firmware"], cwd=tree,
                          capture_output=True, text=True, env=env)
    if done.returncode != 0:
        raise RestampError(f"make firmware in {tree} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")


def smoke_runs(tree: Path, out: Path, progress: bool = True) -> list[Path]:
    """Run the smoke subset with the code of ``tree``, the frame logs written under ``out``;
    returns the logs in a fixed order. Raises RestampError when a run fails."""
    out.mkdir(parents=True, exist_ok=True)
    disturbed = out / "dlc_smoke_disturbed.toml"
    disturbed.write_text(DISTURBED_SMOKE.format(path=(tree / "hil" / "paths" / "dlc.csv").resolve()))
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    python = str((tree / ".venv" / "bin" / "python").absolute())
    logs = []
    for ecu, controllers in SMOKE_CONTROLLERS.items():
        for controller in controllers:
            for scenario in ("dlc_smoke", str(disturbed)):
                log = out / f"{ecu}_{controller}_{Path(scenario).stem}.log"
                command = [python, "-m", "hil", "run", "--scenario", scenario, "--controller", controller,
                           "--ecu", ecu, "--log", str(log), "--replace"]
                if progress:
                    print(f"  {tree.name}: {ecu} {controller} {Path(scenario).stem}", flush=True)
                done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True,
                                      timeout=RUN_TIMEOUT_S)
                if done.returncode != 0 or not log.is_file():
                    raise RestampError(f"smoke run failed in {tree} ({' '.join(command[1:])}):\n"
                                       f"{done.stderr[-2000:]}")
                logs.append(log)
    return logs


# ---------------------------------------------------------------------------- comparison

def behaviour_frames(log: Path, database: cantools.database.can.Database) -> list[tuple]:
    """The frames of a candump log as (time since the first frame in units of
    :data:`TIME_RESOLUTION_US`, identifier, payload or decoded signals, direction ``"R"`` or
    ``"T"``), sorted by time and identifier, the wall-clock signals of
    :data:`WALL_CLOCK_SIGNALS` left out and the frames of :data:`UNTIMED_FRAMES` at time -1
    (first, in payload order). The log is read by the product's reader
    (`can_defs.log_reader.read_log_frames`). Raises RestampError for a log it cannot read
    whole: a skipped line or a cut file is no proof of the same behaviour."""
    try:
        read = read_log_frames(log)
    except LogFileError as exc:
        raise RestampError(str(exc)) from exc
    if not read.complete:
        raise RestampError(f"{log}: {'; '.join(read.warnings)}")
    frames: list[tuple] = []
    first = None
    for message in read.messages:
        # whole microseconds, as the log writes them: a double of ~1.7e9 s parses to within
        # 0.2 us, so rounding gives back the written digits exactly
        stamp_us = round(message.timestamp * 1_000_000)
        first = stamp_us if first is None else first
        arbitration_id, data = message.arbitration_id, bytes(message.data)
        payload: object = data
        try:
            definition = database.get_message_by_frame_id(arbitration_id)
        except KeyError:
            definition = None
        if definition is not None and definition.name in WALL_CLOCK_SIGNALS:
            signals = definition.decode(data, decode_choices=False, scaling=False)
            payload = tuple(sorted((k, v) for k, v in signals.items()
                                   if k not in WALL_CLOCK_SIGNALS[definition.name]))
        # the log's stamps are wall-clock start + virtual time in a double: a few
        # microseconds of rounding that is not behaviour, below the 1 ms of a lockstep tick
        time = round((stamp_us - first) / TIME_RESOLUTION_US)
        if definition is not None and definition.name in UNTIMED_FRAMES:
            time = -1
        frames.append((time, arbitration_id, payload, "R" if message.is_rx else "T"))
    # nodes' frames of one tick reach the recorder in thread order (an ACK stamped before a
    # plant frame may be logged after it): compare in time order, then by identifier
    return sorted(frames, key=lambda frame: (frame[0], frame[1], frame[3], repr(frame[2])))


def first_difference(base_log: Path, log: Path, database: cantools.database.can.Database) -> str | None:
    """None when the two logs show the same behaviour, else where they first differ."""
    base, now = behaviour_frames(base_log, database), behaviour_frames(log, database)
    for index, (a, b) in enumerate(zip(base, now)):
        if a != b:
            return f"{log.name}: frame {index + 1}: base {a} / now {b}"
    if len(base) != len(now):
        return f"{log.name}: {len(base)} frames at the base, {len(now)} now"
    return None


# ---------------------------------------------------------------------------- restamp

def restamp(chosen: list[Candidate], base: str, command: str, root: Path = provenance.ROOT,
            checked_commit: str | None = None) -> None:
    """Give each of ``chosen`` this checkout's sources and commit (its file unchanged), with
    a ``restamped`` record of the check; ``checked_commit``: the commit the smoke ran on,
    which must still be the checkout's."""
    stamps = provenance.load_manifest(root)
    commit = provenance.git_commit(root)
    if checked_commit is not None and commit != checked_commit:
        raise RestampError(f"the checkout moved from {checked_commit} to {commit} while the smoke ran: "
                           "nothing restamped")
    for candidate in chosen:
        entry = dict(stamps[candidate.path])
        if provenance.file_digest(root / candidate.path) != entry["output_sha256"]:
            raise RestampError(f"{candidate.path} changed since its stamp: rerun `{entry['command']}`")
        digests = provenance.input_digests(entry["inputs"], entry["modules"], root)
        if candidate.digest and provenance.combined_digest(digests) != candidate.digest:
            raise RestampError(f"the sources of {candidate.path} changed while the smoke ran: nothing restamped")
        entry.update(commit=commit, sha256=provenance.combined_digest(digests),
                     sources={key: value[:16] for key, value in digests.items()},
                     restamped={"base": base, "check": command, "changed": list(candidate.changed)})
        stamps[candidate.path] = entry
    provenance.save_manifest(stamps, root)


def drop_known_stale_rows(restamped: set[str], root: Path = provenance.ROOT) -> list[str]:
    """Remove the rows of results/KNOWN_STALE.md whose files were all restamped; returns
    the commands of the rows removed."""
    path = root / "results" / provenance.KNOWN_STALE_NAME
    if not path.is_file():
        return []
    kept, dropped = [], []
    for line in path.read_text().splitlines(keepends=True):
        row = provenance.known_stale_row(line)
        if row is not None and all(name in restamped for name in row.files):
            dropped.append(row.command)
            continue
        kept.append(line)
    path.write_text("".join(kept))
    return dropped


def main(argv: list[str] | None = None) -> int:
    """CLI; returns the exit status (0 restamped or nothing to do, 1 the smoke differs,
    2 bad input)."""
    parser = argparse.ArgumentParser(prog="python -m studies.restamp", description=__doc__.splitlines()[0])
    parser.add_argument("--base", required=True,
                        help="the commit at which the stale files were current (their stamps' commit)")
    parser.add_argument("--workdir", type=Path, default=provenance.ROOT / "build" / "restamp",
                        help="where the base's worktree and the smoke logs go (default build/restamp)")
    parser.add_argument("--dry-run", action="store_true", help="list what would be restamped; run nothing")
    parser.add_argument("--exclude", action="append", default=[], metavar="GLOB",
                        help="leave the results files matching GLOB stale (a path the smoke does not run; repeatable)")
    args = parser.parse_args(argv)
    command = f"python -m studies.restamp --base {args.base}"
    root = provenance.ROOT
    try:
        checked_commit = provenance.git_commit(root)
        if checked_commit.endswith("-dirty"):
            raise RestampError("the checkout has uncommitted changes outside results/: commit them first, "
                               "so that the new stamps name the code that was checked")
        base_tree = base_checkout(args.base, args.workdir.resolve(), root)
        chosen, refused = candidates(base_tree, root)
        chosen, excluded = excluded_candidates(chosen, args.exclude)
        refused.update({c.path: "--exclude: left stale" for c in excluded})
        for name, reason in sorted(refused.items()):
            print(f"not restamped: {name}: {reason}")
        for candidate in chosen:
            print(f"candidate: {candidate.path} (`{candidate.command}`; changed: {', '.join(candidate.changed)})")
        if not chosen or args.dry_run:
            print("nothing to restamp" if not chosen else f"{len(chosen)} candidate(s); --dry-run: nothing run")
            return 0
        build_firmware(root)
        database = cantools.database.load_file(str(root / "can_defs" / "vehicle.dbc"))
        base_logs = smoke_runs(base_tree, args.workdir.resolve() / "logs-base")
        logs = smoke_runs(root, args.workdir.resolve() / "logs-now")
        differences = [d for d in (first_difference(a, b, database) for a, b in zip(base_logs, logs)) if d]
        trainer_only = training_sources(root) - smoke_sources(root)
        models: list[Path] = []
        if not differences and any(set(c.changed) & trainer_only for c in chosen):
            form = default_form(root)
            base_models = training_smoke(base_tree, args.workdir.resolve() / "training-base", form)
            models = training_smoke(root, args.workdir.resolve() / "training-now", form)
            differences = [d for d in (artefact_difference(a, b) for a, b in zip(base_models, models)) if d]
        if differences:
            print("the smoke subset differs from the base; nothing restamped:", file=sys.stderr)
            for line in differences:
                print(f"  {line}", file=sys.stderr)
            return 1
        restamp(chosen, args.base, command, root, checked_commit)
        dropped = drop_known_stale_rows({c.path for c in chosen}, root)
        trained = f" and {len(models)} smoke trainings" if models else ""
        print(f"{len(logs)} smoke runs{trained} equal to the base's; restamped {len(chosen)} results file(s)")
        for removed in dropped:
            print(f"results/{provenance.KNOWN_STALE_NAME}: row of `{removed}` removed")
        return 0
    except (RestampError, TrainingSmokeError, provenance.ProvenanceError, subprocess.SubprocessError,
            OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
