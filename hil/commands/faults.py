"""``python -m hil faults``: one run with injected faults, or the whole campaign.

One run: the scenario's ``[faults]`` table (hil/faults.py) plus faults from flags::

    python -m hil faults --scenario dlc_high_mu --controller eso-dkmpc \\
        --bus kind=silent,sender=plant,start_s=3,duration_s=0.06 \\
        --bus kind=bitflip,rate=0.05,start_s=3 --mass-offset 200 --seed 1

``--bus`` takes ``key=value`` pairs of one ``[[faults.bus]]`` entry (numbers as numbers,
``ids=0x100/0x101``, ``true`` / ``false``); repeatable. It prints the run's verdict
(mode sequence, detection, max |e_Y|, invalid commands, crashes) as JSON.

``--campaign``: every case of hil/fault_cases/catalogue.py (what ``make faults`` runs:
``python -m studies.fault_campaign``, which this option runs with the same options), writing ``results/faults.md``, ``faults.json`` and
``faults_vehicle.png``. The output folder is checked before any run: its parent must
exist, and results of an earlier campaign in it are an error unless ``--replace`` is given
(``make faults`` gives it).
"""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "inject bus / vehicle faults into a run, or run the fault campaign (make faults)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m hil faults``."""
    parser.add_argument("--campaign", action="store_true",
                        help="run the whole campaign (make faults) instead of one run")
    parser.add_argument("--scenario", default="dlc_high_mu",
                        help="scenario TOML file or shipped name (default dlc_high_mu)")
    parser.add_argument("--controller", default="eso-dkmpc", type=str.lower,
                        help="controller of the ECU (any case)")
    parser.add_argument("--bus", action="append", default=[], metavar="K=V,...",
                        help="one bus fault, e.g. kind=drop,rate=0.1,start_s=3 (repeatable)")
    parser.add_argument("--mu-step", default=None, metavar="T:MU",
                        help="road friction step at T s to MU (the plant's mu_step)")
    parser.add_argument("--mass-offset", type=float, default=None, metavar="KG")
    parser.add_argument("--steer-offset", type=float, default=None, metavar="RAD")
    parser.add_argument("--steer-lag", type=float, default=None, metavar="S",
                        help="extra steering actuator time constant")
    parser.add_argument("--rear-stiffness", type=float, default=None, metavar="SCALE",
                        help="factor on the rear tyres' cornering stiffness (e.g. 0.8: 20 %% less)")
    parser.add_argument("--sensor", default=None, metavar="K=V,...",
                        help="sensor fault, e.g. vy_bias=0.05,yaw_rate_noise=0.005")
    parser.add_argument("--seed", type=int, default=None, help="seed of the random faults")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="shorten the scenario (s)")
    parser.add_argument("--out", type=Path, default=Path("results"),
                        help="campaign output folder (default results; its parent must exist)")
    parser.add_argument("--replace", action="store_true",
                        help="campaign: overwrite the results of an earlier campaign in --out")
    parser.add_argument("--only", nargs="+", default=None, metavar="NAME",
                        help="campaign: only these cases")
    parser.add_argument("--controllers", nargs="+", default=None, type=str.lower,
                        help="campaign: only these controllers (any case)")
    parser.add_argument("--workers", type=int, default=None,
                        help="campaign: run on a local Ray with this many workers (default: "
                             "in this process); the wall-clock cases still run alone")
    parser.add_argument("--address", default=None,
                        help="campaign: run on the Ray cluster at auto, HOST:PORT or ray://HOST:PORT")
    parser.add_argument("--serial", action="store_true", help="campaign: in this process (the default)")


def _value(text: str) -> object:
    if text in ("true", "false"):
        return text == "true"
    if "/" in text:
        return [_value(part) for part in text.split("/")]
    for parse in (lambda t: int(t, 0), float):
        try:
            return parse(text)
        except ValueError:
            continue
    return text


def parse_pairs(text: str, flag: str) -> dict[str, object]:
    """``a=1,b=x`` -> {"a": 1, "b": "x"} (``ids`` always a list)."""
    from hil.faults import FaultSpecError

    table: dict[str, object] = {}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise FaultSpecError(f"{flag} {text!r}: {item!r} is not key=value")
        table[key.strip()] = _value(value.strip())
    if "ids" in table and not isinstance(table["ids"], list):
        table["ids"] = [table["ids"]]
    return table


def faults_table(args: argparse.Namespace, base: dict) -> dict:
    """The scenario's ``[faults]`` table with the flags' faults added."""
    from hil.faults import FaultSpecError

    table = {k: (list(v) if k == "bus" else dict(v) if isinstance(v, dict) else v)
             for k, v in base.items()}
    table.setdefault("bus", [])
    table["bus"] = list(table["bus"]) + [parse_pairs(b, "--bus") for b in args.bus]
    vehicle = dict(table.get("vehicle", {}))
    for key, value in (("mass_offset_kg", args.mass_offset), ("steer_offset_rad", args.steer_offset),
                       ("steer_extra_lag_s", args.steer_lag),
                       ("cornering_stiffness_rear_scale", args.rear_stiffness)):
        if value is not None:
            vehicle[key] = value
    if vehicle:
        table["vehicle"] = vehicle
    if args.sensor:
        table["sensor"] = {**table.get("sensor", {}), **parse_pairs(args.sensor, "--sensor")}
    if args.mu_step:
        time_s, sep, mu = args.mu_step.partition(":")
        try:
            table["mu_step"] = {"time_s": float(time_s), "mu": float(mu)}
        except ValueError:
            raise FaultSpecError(f"--mu-step {args.mu_step!r}: expected T:MU, e.g. 3.0:0.5") from None
        if not sep:
            raise FaultSpecError(f"--mu-step {args.mu_step!r}: expected T:MU, e.g. 3.0:0.5")
    if args.seed is not None:
        table["seed"] = args.seed
    return table


def main(args: argparse.Namespace) -> int:
    """Run one faulted scenario (print its verdict) or the campaign."""
    import dataclasses
    import json

    from hil.fault_cases.catalogue import FaultCase
    from hil.fault_cases.runs import run_case
    from hil.scenario import load_scenario

    if args.campaign:
        return run_campaign_command(args)
    scenario = load_scenario(args.scenario)
    table = faults_table(args, dict(scenario.faults))
    group = "bus" if table.get("bus") else "vehicle"
    case = FaultCase("cli", group, table, (args.controller,))
    verdict = run_case(case, args.controller, args.scenario, args.duration,
                       source=f"{scenario.source} + flags")
    row = dataclasses.asdict(verdict)
    row.pop("e_y")
    row.pop("time_s")
    row["passed"] = verdict.passed()
    print(json.dumps(row, indent=2))
    return 1 if verdict.crashes or verdict.invalid_commands else 0


def campaign_argv(args: argparse.Namespace) -> list[str]:
    """The options of ``python -m studies.fault_campaign`` that ``--campaign`` was given."""
    argv = ["--out", str(args.out)]
    argv += ["--replace"] if args.replace else []
    argv += ["--only", *args.only] if args.only else []
    argv += ["--controllers", *args.controllers] if args.controllers else []
    argv += ["--duration", repr(args.duration)] if args.duration is not None else []
    argv += ["--workers", str(args.workers)] if args.workers is not None else []
    argv += ["--address", args.address] if args.address else []
    argv += ["--serial"] if args.serial else []
    return argv


def run_campaign_command(args: argparse.Namespace) -> int:
    """``--campaign``: the study's own command (``make faults``), run as a process so that
    hil, below the studies, imports none of them; its exit status is this one's."""
    import subprocess
    import sys

    return subprocess.call([sys.executable, "-m", "studies.fault_campaign", *campaign_argv(args)])
