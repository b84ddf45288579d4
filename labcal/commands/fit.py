"""`labcal fit`: coefficients, their uncertainty, intervals, replication and extension tests."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labcal.commands.common import out, print_json
from labcal.errors import LabcalError

if TYPE_CHECKING:
    from rich.table import Table

EXTENSION_NAMES = ("temperature", "harmonics")  # labcal.analysis.models.EXTENSIONS, for the help


def parse_at(text: str) -> tuple[float, float, float, float]:
    """'PITCH,ROLL[,Y,U]' in degrees."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise LabcalError(f"--at {text!r}: expected PITCH,ROLL or PITCH,ROLL,Y,U in degrees") from None
    if len(values) not in (2, 4):
        raise LabcalError(f"--at {text!r}: expected PITCH,ROLL or PITCH,ROLL,Y,U in degrees")
    if len(values) == 2:
        pitch, roll = values
        return pitch, roll, 0.0, 0.0
    pitch, roll, y, u = values
    return pitch, roll, y, u


def cmd_fit(args: argparse.Namespace) -> int:
    import numpy as np

    from labcal.analysis.coning import coning, coning_json
    from labcal.analysis.fit import SENSORS, extension_tests, fit_readings, reference_temperature
    from labcal.analysis.models import Model, Points
    from labcal.config.readings_csv import read_readings

    readings = read_readings(args.readings)
    extend = tuple(e.strip() for e in args.extend.split(",") if e.strip()) if args.extend else ()
    fit = fit_readings(readings, Model(extend, reference_temperature(readings)))
    doc = coning_json(fit) if args.model == "coning" else fit.to_json()
    at = [parse_at(a) for a in args.at or []]
    if at:
        points = Points.at(*np.array(at).T)
        pred = fit.predict(points, args.level)
        doc["predictions"] = [
            {"pitch_deg": p[0], "roll_deg": p[1], "y_deg": p[2], "u_deg": p[3],
             "volts": pred["volts"][i].tolist(), "level": args.level,
             "confidence_half_width": pred["confidence"][i].tolist(),
             "prediction_half_width": pred["prediction"][i].tolist()}
            for i, p in enumerate(at)]
    if args.test_extensions:
        doc["extension_tests"] = {t.name: t.to_json() for t in extension_tests(readings)}
    if args.json:
        print_json(doc)
        return 0
    from labcal.commands.console import coefficients_with_standard_errors

    out.print(coefficients_with_standard_errors(fit))
    for note in fit.notes:
        out.print(f"[yellow]note:[/] {note}")
    if args.model == "coning":
        out.print(coning_table(coning(fit)))
    if fit.replication is not None:
        out.print(replication_table(doc["replication"]))
    for p in doc.get("predictions", []):
        out.print(f"at pitch {p['pitch_deg']:g}°, roll {p['roll_deg']:g}°, mount y={p['y_deg']:g} "
                  f"u={p['u_deg']:g}: " + "; ".join(
                      f"v{s} = {v:+.7f} V ± {c:.2g} (confidence) ± {q:.2g} (prediction)"
                      for s, v, c, q in zip(SENSORS, p["volts"], p["confidence_half_width"],
                                            p["prediction_half_width"], strict=True))
                  + f" at {p['level']:.0%}")
    for name, test in doc.get("extension_tests", {}).items():
        if not test["tested"]:
            out.print(f"extension {name}: not tested — {test['reason']}")
        else:
            verdict = ", ".join(f"{s} {'warranted' if w else 'not warranted'} (p = {p:.2g})"
                                for s, w, p in zip(SENSORS, test["warranted"], test["p_value"], strict=True))
            out.print(f"extension {name}: F test with df {tuple(test['df'])}: {verdict}")
    return 0


def coning_table(sensors) -> Table:
    from rich.table import Table

    table = Table(title="Coning model (Tripp eq. 2): v = b + S·(u·g)")
    for col in ("sensor", "b (V)", "S (V/g)", "Ω (°)", "A (°)"):
        table.add_column(col, justify="right")
    for c in sensors:
        d = c.to_json()
        se = d["standard_errors"]
        azimuth = (f"{d['azimuth_deg']:.3f} ± {se['azimuth_deg']:.2g}" if d["azimuth_deg"] is not None
                   else "undefined (Ω ≈ 0)")
        table.add_row(c.name, f"{d['b']:+.7f} ± {se['b']:.2g}", f"{d['S']:.7f} ± {se['S']:.2g}",
                      f"{d['omega_deg']:.5f} ± {se['omega_deg']:.2g}", azimuth)
    return table


def replication_table(rep: dict) -> Table:
    from rich.table import Table

    table = Table(title="Replicated calibration (Tripp Table 2)")
    for col in ("sensor", "σ_prec (V)", "σ_bias (V)", "lack of fit F (df) crit", "offset drift F",
                "sens. drift F"):
        table.add_column(col, justify="right")
    for sensor, r in rep.items():
        lof, off, sens = r["lack_of_fit"], r["drift"].get("offset"), r["drift"].get("sensitivity")

        def flag(t):
            return "—" if t is None else f"{t['F']:.3g}{' *' if t['significant'] else ''}"
        table.add_row(sensor, f"{r['sigma_prec']:.3g}", f"{r['sigma_bias']:.3g}",
                      f"{lof['F']:.3g}{' *' if lof['significant'] else ''} ({lof['df'][0]}, {lof['df'][1]}) "
                      f"{lof['critical_95']:.3g}", flag(off), flag(sens))
    table.caption = "* significant at 5 %"
    return table


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit calibration coefficients to a readings CSV",
                       description="Least-squares fit of V = B + gᵀS on the nominal gravity "
                                   "(Soto eqs. 13–21) with standard errors, full covariance, replicated-"
                                   "calibration analysis (Tripp & Tcheng §8) and, on request, the coning "
                                   "model and intervals.")
    p.add_argument("readings", help="readings CSV (replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz)")
    p.add_argument("--model", choices=["linear", "coning"], default="linear",
                   help="linear: Soto's X; coning: per sensor b, S, Ω, A (Tripp eq. 2)")
    p.add_argument("--extend", metavar="NAMES",
                   help=f"extra regressors, comma-separated: {', '.join(EXTENSION_NAMES)}")
    p.add_argument("--test-extensions", action="store_true",
                   help="F test whether each extension is warranted")
    p.add_argument("--at", action="append", metavar="PITCH,ROLL[,Y,U]",
                   help="predicted output with confidence and prediction intervals here (repeatable)")
    p.add_argument("--level", type=float, default=0.95, help="interval level (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the fit as JSON on stdout")
    p.set_defaults(func=cmd_fit)
