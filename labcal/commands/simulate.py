"""`labcal simulate`: readings from a plan and a known truth, no sequencer."""

from __future__ import annotations

import argparse
import os
from typing import TYPE_CHECKING

from labcal.analysis import kinematics
from labcal.analysis.kinematics import IndexWobble
from labcal.commands import summary
from labcal.commands.common import SEED, bounded, err, print_json
from labcal.config.emulation import InstrumentTruth
from labcal.config.files import load_model
from labcal.config.plans import load_plan
from labcal.config.readings_csv import write_readings
from labcal.errors import LabcalError
from labcal.sim.direct import simulate_readings

if TYPE_CHECKING:
    from labcal.analysis.kinematics import Misalignment

UNITS_DEG = {"arcsec": 1 / 3600, "″": 1 / 3600, '"': 1 / 3600, "deg": 1.0, "°": 1.0}


def parse_angle(name: str, text: str) -> float:
    """'60arcsec', '60″', '0.01deg', '0.01°' → degrees; a bare number is degrees (as before units)."""
    text = text.strip()
    unit = next((u for u in UNITS_DEG if text.endswith(u)), "")
    number = text[: len(text) - len(unit)].strip()
    try:
        value = float(number) * UNITS_DEG.get(unit, 1.0)
    except ValueError:
        raise LabcalError(f"--misalign: {number!r} for {name} is not a number; write e.g. {name}=60arcsec "
                          f"or {name}=0.01deg") from None
    if not abs(value) <= 5:
        raise LabcalError(f"--misalign: {name}={text} is not a small misalignment (|x| ≤ 5°)")
    return value


def parse_misalign(text: str) -> Misalignment:
    """'a=60arcsec,k=0.01deg' (units arcsec/″ or deg/°; bare numbers are degrees) → Misalignment."""
    angles: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep or name not in kinematics.MISALIGNMENT_NAMES:
            raise LabcalError(f"--misalign: {part!r} is not NAME=ANGLE with NAME one of "
                              f"{', '.join(kinematics.MISALIGNMENT_NAMES)} (e.g. a=60arcsec,k=0.01deg)")
        angles[name] = parse_angle(name, value)
    return kinematics.Misalignment.from_degrees(**angles)


def cmd_simulate(args: argparse.Namespace) -> int:
    if os.path.lexists(args.out) and not args.force:  # it may be a measured file: replace it only if told
        raise LabcalError(f"{args.out}: exists; choose another --out, or give --force to replace it")
    plan, _ = load_plan(args.plan)
    if args.replicates is not None:
        plan = plan.model_copy(update={"replicates": args.replicates})
    truth = load_model(args.truth, InstrumentTruth, "truth") if args.truth else InstrumentTruth()
    readings = simulate_readings(
        plan, truth, parse_misalign(args.misalign),
        IndexWobble(args.index_error, args.wobble, args.seed), args.noise, args.seed)
    try:
        write_readings(args.out, readings)
    except OSError as exc:
        raise LabcalError(f"{args.out}: cannot write readings ({exc.strerror})") from None
    if args.json:
        print_json({"out": args.out, "readings": len(readings), "plan": plan.name, "noise_v": args.noise,
                    "seed": args.seed})
    else:
        err.print(f"{len(readings)} readings written to {args.out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help=summary("simulate"),
                       description="Readings from a plan and a known truth, no sequencer: exact "
                                   "with --noise 0 and no index/wobble errors.")
    p.add_argument("--plan", default="four-mount-64", help="plan name or .toml file")
    p.add_argument("--misalign", default="", metavar="a=60arcsec,k=0.01deg,...",
                   help="CD misalignments a, b, d, e, f, k with their unit: arcsec (or ″) or deg (or °); "
                        "a number without a unit is degrees")
    p.add_argument("--truth", help="TOML with the instrument's B = [..] and S = [[..],[..],[..]] "
                                   "(default ideal: B = 0, S = I)")
    p.add_argument("--noise", type=bounded(float, 0, 10), default=0.0,
                   help="white noise per reading, V rms (0..10)")
    p.add_argument("--index-error", type=bounded(float, 0, 3600), default=0.0, metavar="ARCSEC",
                   help="amplitude of the tables' per-point index errors, arcseconds (a fixed function of "
                        "each table's angle, zero mean)")
    p.add_argument("--wobble", type=bounded(float, 0, 3600), default=0.0, metavar="ARCSEC",
                   help="amplitude of the tables' per-point wobble errors, arcseconds")
    p.add_argument("--replicates", type=bounded(int, 1, 100), metavar="N",
                   help="repeat the plan N times (default: the plan's own replicates)")
    p.add_argument("--seed", type=SEED, default=0, help="random seed")
    p.add_argument("--out", required=True, help="readings CSV to write (refused if it exists, unless "
                                                     "--force)")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.add_argument("--json", action="store_true", help="print what was written as JSON on stdout")
    p.set_defaults(func=cmd_simulate)
