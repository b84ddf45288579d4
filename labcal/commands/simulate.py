"""`labcal simulate`: readings from a plan and a known truth, no sequencer."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labcal.commands.common import err
from labcal.errors import LabcalError

if TYPE_CHECKING:
    from labcal.analysis.kinematics import Misalignment


def parse_misalign(text: str) -> Misalignment:
    """'a=0.3,b=-0.2' (degrees) → Misalignment."""
    from labcal.analysis.kinematics import MISALIGNMENT_NAMES, Misalignment

    angles: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep or name not in MISALIGNMENT_NAMES:
            raise LabcalError(f"--misalign: {part!r} is not NAME=DEGREES with NAME one of "
                              f"{', '.join(MISALIGNMENT_NAMES)}")
        try:
            angles[name] = float(value)
        except ValueError:
            raise LabcalError(f"--misalign: {value.strip()!r} for {name} is not a number") from None
        if not abs(angles[name]) <= 5:
            raise LabcalError(f"--misalign: {name}={value.strip()}° is not a small misalignment (|x| ≤ 5°)")
    return Misalignment.from_degrees(**angles)


def cmd_simulate(args: argparse.Namespace) -> int:
    from labcal.analysis.kinematics import IndexWobble
    from labcal.config.emulation import InstrumentTruth
    from labcal.config.files import load_model
    from labcal.config.plans import load_plan
    from labcal.config.readings_csv import write_readings
    from labcal.sim.direct import simulate_readings

    plan, _ = load_plan(args.plan)
    truth = load_model(args.truth, InstrumentTruth, "truth") if args.truth else InstrumentTruth()
    if args.noise < 0:
        raise LabcalError("--noise must be ≥ 0 (V rms)")
    readings = simulate_readings(
        plan, truth, parse_misalign(args.misalign),
        IndexWobble(args.index_error, args.wobble, args.seed), args.noise, args.seed)
    try:
        write_readings(args.out, readings)
    except OSError as exc:
        raise LabcalError(f"{args.out}: cannot write readings ({exc.strerror})") from None
    err.print(f"{len(readings)} readings written to {args.out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="write readings straight from a plan and a truth",
                       description="Readings from a plan and a known truth, no sequencer: exact "
                                   "with --noise 0 and no index/wobble errors.")
    p.add_argument("--plan", default="four-mount-64", help="plan name or .toml file")
    p.add_argument("--misalign", default="", metavar="a=DEG,b=DEG,...",
                   help="CD misalignments in degrees (names a, b, d, e, f, k)")
    p.add_argument("--truth", help="TOML with the instrument's B = [..] and S = [[..],[..],[..]] "
                                   "(default ideal: B = 0, S = I)")
    p.add_argument("--noise", type=float, default=0.0, help="white noise per reading, V rms")
    p.add_argument("--index-error", type=float, default=0.0, metavar="ARCSEC",
                   help="amplitude of the tables' index errors")
    p.add_argument("--wobble", type=float, default=0.0, metavar="ARCSEC",
                   help="amplitude of the tables' wobble errors")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--out", required=True, help="readings CSV to write")
    p.set_defaults(func=cmd_simulate)
