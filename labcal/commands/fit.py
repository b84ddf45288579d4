"""`labcal fit`: coefficients, their uncertainty, intervals, replication and extension tests."""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import bounded, keep_freed_memory, out, outcome_of_checks, print_json
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    import numpy as np
    from rich import box
    from rich import table as rich_table
    from rich.table import Table

    from labcal.analysis import (
        attitude,
        budget,
        declared_noise,
        device_fit,
        distributions,
        gross_errors,
        index_errors,
        kinematics,
        lack_of_fit,
        models,
        packages,
    )
    from labcal.analysis import coning as analysis_coning
    from labcal.analysis import fit as analysis_fit
    from labcal.commands import console
    from labcal.config import readings_csv, station
else:
    analysis_coning = lazy("labcal.analysis.coning")  # start-up without scipy, numpy
    analysis_fit = lazy("labcal.analysis.fit")  # start-up without scipy, numpy
    attitude = lazy("labcal.analysis.attitude")  # start-up without scipy, numpy
    box = lazy("rich.box")  # start-up without rich
    budget = lazy("labcal.analysis.budget")  # start-up without scipy, numpy
    console = lazy("labcal.commands.console")  # rich, which --json does not need
    declared_noise = lazy("labcal.analysis.declared_noise")  # start-up without scipy, numpy
    device_fit = lazy("labcal.analysis.device_fit")  # start-up without scipy, numpy
    distributions = lazy("labcal.analysis.distributions")  # start-up without scipy, numpy
    gross_errors = lazy("labcal.analysis.gross_errors")  # start-up without scipy, numpy
    index_errors = lazy("labcal.analysis.index_errors")  # start-up without scipy, numpy
    kinematics = lazy("labcal.analysis.kinematics")  # start-up without numpy
    lack_of_fit = lazy("labcal.analysis.lack_of_fit")  # start-up without scipy, numpy
    models = lazy("labcal.analysis.models")  # start-up without numpy
    np = lazy("numpy")  # start-up without numpy
    packages = lazy("labcal.analysis.packages")  # start-up without scipy, numpy
    readings_csv = lazy("labcal.config.readings_csv")  # start-up without scipy, numpy, pydantic
    rich_table = lazy("rich.table")  # start-up without rich
    station = lazy("labcal.config.station")  # start-up without scipy, numpy, pydantic

EXTENSION_NAMES = ("temperature", "harmonics")  # labcal.analysis.models.EXTENSIONS, for the help


def parse_at(text: str) -> tuple[float, float, float, float]:
    """'PITCH,ROLL[,Y,U]' in degrees."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise LabcalError(f"--at {text!r}: expected PITCH,ROLL or PITCH,ROLL,Y,U in degrees") from None
    if len(values) not in (2, 4):
        raise LabcalError(f"--at {text!r}: expected PITCH,ROLL or PITCH,ROLL,Y,U in degrees")
    if not all(math.isfinite(v) for v in values):
        raise LabcalError(f"--at {text!r}: every angle must be a finite number of degrees")
    pitch, roll, y, u = values if len(values) == 4 else (*values, 0.0, 0.0)
    if not (-360 <= pitch <= 360 and -360 <= roll <= 360):
        raise LabcalError(f"--at {text!r}: pitch and roll must be within -360..360°")
    if y % 360 not in (0, 180) or u % 360 not in (0, 180):
        raise LabcalError(f"--at {text!r}: the mount Y,U must each be 0 or 180 (a mount is {y:g},{u:g})")
    return pitch, roll, y, u


def singular_sensitivity(X, source: str) -> None:
    """Refuse, naming the readings file, a fit whose S cannot turn voltages into g: every check and
    estimate after it inverts S."""
    defect = attitude.sensitivity_defect(X)
    if defect:
        raise LabcalError(f"{source}: {defect}")


def choose_model(args: argparse.Namespace, readings) -> tuple[str, str | None]:
    """The model to fit and, when it was chosen for the user, the one line saying why."""
    if args.index_errors and args.model not in (None, "device"):
        raise LabcalError("--index-errors extends the device model; leave out --model or give --model device")
    if (args.table_index or args.table_wobble) and args.model not in (None, "device"):
        raise LabcalError("--table-index and --table-wobble are the device model's; leave out --model or "
                          "give --model device")
    if args.model == "device" and (args.extend or args.at):
        raise LabcalError("--extend and --at work with the linear and coning models; leave them out "
                          "with --model device")
    if args.model is not None:
        return args.model, None
    model, note = device_fit.default_model(readings)
    if model == "device" and (args.extend or args.at):
        return "linear", "linear model: --extend and --at need it (--model device fits the misalignments)"
    return model, note + ("; " + device_fit.LINEAR_HINT if model == "device" else "")


def against_station(args: argparse.Namespace, readings, fit, doc: dict, flags: list) -> list:
    """--station FILE: the residual against what the station declares (`labcal.analysis.declared_noise`:
    its settle noise per sample and samples per point, its tables' index and wobble), in ``doc`` as
    "declared_noise"; the readings it names that the gross-error ``flags`` do not already."""
    if not args.station:
        return []
    config, _ = station.load_station(args.station)
    if readings.units != "V":
        raise LabcalError(f"--station: the station declares its noise in volts, the readings are in "
                          f"{readings.units}")
    u, settle = config.uncertainty, config.sequencer.settle
    errors = device_fit.AngleErrors(u.pitch_index, u.pitch_wobble, u.roll_index, u.roll_wobble)
    if not errors:
        doc["declared_noise"] = {"made": False, "summary": declared_noise.NO_ANGLE_ERRORS}
        return []
    declared = declared_noise.Declared.of(settle.noise_v, settle.samples, errors)
    check = declared_noise.noise_check(readings, fit.coefficients[1:], declared)
    doc["declared_noise"] = {"made": True, **check.to_json(), "summary": check.summary(readings.units)}
    if check.passed:
        return []
    seen = {f.row for f in flags}
    return [f for f in check.flags if f.row not in seen]


def cmd_fit(args: argparse.Namespace) -> int:
    keep_freed_memory()
    readings = readings_csv.read_readings(args.readings, args.units)
    gross_errors.implausible_volts(readings.volts, readings.units)
    model, chosen = choose_model(args, readings)
    checked = None  # (the linear fit, its gross-error flags), computed once for the choice and the device fit
    if model == "device":
        linear = analysis_fit.fit_readings(readings)
        singular_sensitivity(linear.coefficients, args.readings)
        checked = linear, gross_errors.fit_flags(readings, linear)
        if checked[1] and args.model is None:
            model, chosen = "linear", ("linear model: some readings fail the gross-error checks (listed "
                                       "below); the device model is fitted only to readings that pass them")
    if model == "device":
        return fit_device_model(args, readings, chosen, checked)
    extend = tuple(e.strip() for e in args.extend.split(",") if e.strip()) if args.extend else ()
    fit = analysis_fit.fit_readings(
        readings, models.Model(extend, analysis_fit.reference_temperature(readings))
    )
    singular_sensitivity(fit.coefficients, args.readings)
    doc = analysis_coning.coning_json(fit) if model == "coning" else fit.to_json()
    doc["units"] = readings.units  # B and S_E in these, S in these per g
    if chosen:
        doc.setdefault("notes", []).insert(0, chosen)
    if fit.sensors != analysis_fit.SENSORS:  # a package: its sensors as Tripp & Tcheng state them (eq. 8)
        doc["package"] = {"package": packages.package_of(fit.sensors), "sensors": {
            s.axis: {"b": s.b, "S": s.S, "omega_deg": float(np.degrees(s.omega)),
                     "azimuth_deg": float(np.degrees(s.azimuth))} for s in packages.sensors_of(fit)}}
    flags = gross_errors.fit_flags(readings, fit)
    doc["gross_errors"] = [f.to_json() for f in flags]
    flags += against_station(args, readings, fit, doc, flags)
    at = [parse_at(a) for a in args.at or []]
    if at:
        points = models.Points.at(*np.array(at).T)
        pred = fit.predict(points, args.level)
        doc["predictions"] = [
            {"pitch_deg": p[0], "roll_deg": p[1], "y_deg": p[2], "u_deg": p[3],
             "volts": pred["volts"][i].tolist(), "level": args.level,
             "confidence_half_width": pred["confidence"][i].tolist(),
             "prediction_half_width": pred["prediction"][i].tolist()}
            for i, p in enumerate(at)]
    if args.test_extensions:
        doc["extension_tests"] = {t.name: t.to_json() for t in analysis_fit.extension_tests(readings)}
    doc["lack_of_fit"] = lack_of_fit_doc(readings, fit)
    if args.json:
        print_json(doc)
        return outcome_of_checks(flags, args.allow_outliers, args.readings)
    out.print(console.coefficients_with_standard_errors(fit, units=readings.units))
    if (terms := console.extension_terms(fit)) is not None:
        out.print(terms)
    for note in doc.get("notes", []):
        out.print(f"[yellow]note:[/] {note}")
    if "package" in doc:
        said = "; ".join(f"sensor {a}: b = {c['b']:.6g}, S = {c['S']:.6g}, Ω = {c['omega_deg']:.4g}°, "
                         f"A = {c['azimuth_deg']:.4g}°" for a, c in doc["package"]["sensors"].items())
        out.print(f"{doc['package']['package']} package (Tripp & Tcheng eq. 8): {said}", markup=False)
    if "declared_noise" in doc:
        out.print(f"against the station: {doc['declared_noise']['summary']}", markup=False)
    if model == "coning":
        out.print(coning_table(analysis_coning.coning(fit), readings.units))
    if fit.replication is not None:
        out.print(replication_table(doc["replication"], readings.units, doc["residual_standard_error"]))
    k = distributions.t_quantile(0.5 + args.level / 2, fit.variance_dof)  # the half-widths' coverage factor
    for p in doc.get("predictions", []):
        out.print(f"at pitch {p['pitch_deg']:g}°, roll {p['roll_deg']:g}°, mount y={p['y_deg']:g} "
                  f"u={p['u_deg']:g}, {p['level']:.1%} intervals:")
        for j, (s, v, c, q) in enumerate(zip(fit.sensors, p["volts"], p["confidence_half_width"],
                                             p["prediction_half_width"], strict=True)):
            value = console.with_standard_error(v, c / k[j]).split(" ±")[0]  # to the digits its SE supports
            out.print(f"  v{s} = {value} {readings.units}; confidence ± {c:.2g}, prediction ± {q:.2g} "
                      f"(k = {k[j]:.2f})")
    for name, test in doc.get("extension_tests", {}).items():
        if not test["tested"]:
            out.print(f"extension {name}: not tested — {test['reason']}")
        else:
            verdict = ", ".join(f"{s} {'warranted' if w else 'not warranted'} (p = {p:.2g})"
                                for s, w, p in zip(fit.sensors, test["warranted"], test["p_value"],
                                                   strict=True))
            out.print(f"extension {name}: F test with df {tuple(test['df'])}: {verdict}")
    print_lack_of_fit(doc["lack_of_fit"])
    return outcome_of_checks(flags, args.allow_outliers, args.readings)


def fit_device_model(args: argparse.Namespace, readings, chosen: str | None, checked=None) -> int:
    """`labcal fit --model device`: the instrument and the device's six misalignments together."""
    index, wobble = args.table_index * kinematics.ARCSEC, args.table_wobble * kinematics.ARCSEC
    fit = device_fit.fit_device(
        readings, checked[0] if checked else None, device_fit.AngleErrors(index, wobble, index, wobble)
    )
    doc = fit.to_json()
    doc["units"] = readings.units  # B and S_E in these, S in these per g
    # what physics guarantees, whichever model is fitted (the same linear fit: the same flags)
    flags = checked[1] if checked else gross_errors.fit_flags(readings, fit.linear)
    doc["gross_errors"] = [f.to_json() for f in flags]
    flags = [*flags, *against_station(args, readings, fit.linear, doc, flags)]
    if args.index_errors:
        extension = index_errors.fit_index_errors(readings, fit)
        doc["index_errors"] = None if extension is None else extension.to_json()
    # the readings' own notes (noise-free data) hold whichever model is fitted
    exact = [n for n in fit.linear.notes if n.startswith(analysis_fit.NOISE_FREE)]
    doc["notes"] = [*([chosen] if chosen else []), *exact, *doc.get("notes", [])]
    if not doc["notes"]:
        del doc["notes"]
    if args.test_extensions:
        doc["extension_tests"] = {t.name: t.to_json() for t in analysis_fit.extension_tests(readings)}
    doc["lack_of_fit"] = lack_of_fit_doc(readings, fit.linear, fit, index, wobble)
    if args.json:
        print_json(doc)
        return outcome_of_checks(flags, args.allow_outliers, args.readings)
    for table in console.device_tables(doc):
        out.print(table)
    for note in doc.get("notes", []):
        out.print(f"[yellow]note:[/] {note}")
    if "package" in doc:
        said = "; ".join(f"sensor {a}: b = {c['b']:.6g}, S = {c['S']:.6g}, Ω = {c['omega_deg']:.4g}°, "
                         f"A = {c['azimuth_deg']:.4g}°" for a, c in doc["package"]["sensors"].items())
        out.print(f"{doc['package']['package']} package (Tripp & Tcheng eq. 8): {said}", markup=False)
    if "declared_noise" in doc:
        out.print(f"against the station: {doc['declared_noise']['summary']}", markup=False)
    if fit.linear.replication is not None:
        linear = fit.linear.to_json()
        out.print(replication_table(linear["replication"], readings.units, linear["residual_standard_error"]))
    for sensor, r in doc.get("replication", {}).items():
        before, after = r["lack_of_fit_linear"], r["lack_of_fit_device"]
        def n(x, spec: str) -> str:  # NaN or None: undefined (noise-free readings)
            return "undefined" if x is None or x != x else format(x, spec)
        out.print(f"sensor {sensor}: σ_bias {r['sigma_bias_linear']:.3g} → {r['sigma_bias_device']:.3g} "
                  f"{readings.units}, lack of fit F {n(before['F'], '.3g')} "
                  f"(p = {n(before['p_value'], '.2g')}) → {n(after['F'], '.3g')} "
                  f"(p = {n(after['p_value'], '.2g')}), linear → device model")
    if args.index_errors:
        out.print(index_error_text(doc["index_errors"]))
    print_lack_of_fit(doc["lack_of_fit"])
    return outcome_of_checks(flags, args.allow_outliers, args.readings)


def lack_of_fit_doc(readings, fit, device=None, index: float = 0.0, wobble: float = 0.0) -> dict:
    """The lack-of-fit and drift tests of the fit (`labcal.analysis.lack_of_fit`) against the noise the
    readings' windows show and the tables' stated index and wobble (--table-index, --table-wobble):
    a flag, not a failure of the command — the coefficients are what the readings give, and the
    certificate of a run states the same flag."""
    if len(readings) > lack_of_fit.MAX_READINGS:
        return {
            "tested": False,
            "reason": f"more than {lack_of_fit.MAX_READINGS} readings: not a calibration run",
        }
    if len(fit.sensors) < 3:  # the test weighs the three sensors' residuals together (their |g|)
        return {"tested": False, "reason": f"a package of the {', '.join(fit.sensors)} sensor(s): the test "
                                           "is made of three sensors' residuals together; Table 2's "
                                           "replicated analysis above tests each sensor's lack of fit"}
    cal = (
        budget.calibration_of(fit, readings)
        if device is None
        else budget.calibration_of_device(device, readings)
    )
    check = lack_of_fit.fit_lack_of_fit(
        cal,
        budget.TypeBInputs(pitch_index=index, pitch_wobble=wobble, roll_index=index, roll_wobble=wobble),
        readings,
        fit,
        device,
    )
    if check is None:
        return {"tested": False, "reason": "the readings do not carry their windows' scatter (the audit "
                                           "columns n_samples, sd_vx, sd_vy, sd_vz labcal writes)"}
    return {"tested": True, "significant": check.significant, "statistic": check.statistic,
            "df": list(check.dof), "p_value": check.p_value, "alpha": check.alpha,
            "bench": {b.name: {"ratio": b.ratio, "p_value": b.p_value} for b in check.bench},
            "bench_errors_stated": bool(index or wobble),
            "drift": {"significant": check.drift_significant, "chi2": check.drift_statistic,
                      "df": check.drift_dof, "p_value": check.drift_p_value}}


def print_lack_of_fit(doc: dict) -> None:
    """One line for the lack-of-fit test and one for the drift test."""
    if not doc["tested"]:
        out.print(f"lack of fit: not tested — {doc['reason']}")
        return
    against = "the windows' noise" + (" and the tables' stated index and wobble" if doc["bench_errors_stated"]
                                      else " alone (no bench error stated: --table-index, --table-wobble)")
    df = tuple(round(d) for d in doc["df"])
    figures = f"Q/ν = {doc['statistic']:.3g}, df {df}, p = {doc['p_value']:.2g}"
    if doc["significant"]:
        out.print(f"[bold red]LACK OF FIT[/] against {against} ({figures}): the residuals hold an effect the "
                  "model or the stated errors leave out")
    else:
        out.print(f"lack of fit: none against {against} ({figures})")
    d = doc["drift"]
    out.print(("[bold red]DRIFT[/]" if d["significant"] else "drift: none") +
              f" (trend of each output over the readings' order, χ² {d['chi2']:.3g}, df {d['df']}, "
              f"p = {d['p_value']:.2g})")


def index_error_text(doc: dict | None) -> str:
    if doc is None:
        return "index errors: this plan leaves no per-angle index error identifiable"
    test = doc["test"]
    lines = [f"index errors (per visited angle, zero mean per table): F = {test['F']:.3g}, "
             f"df {tuple(test['df'])}, p = {test['p_value']:.2g}: "
             + ("accepted" if doc["accepted"] else "not warranted")]
    for table in ("pitch_table", "roll_table"):
        cells = ", ".join(f"{a['angle_deg']:g}°: {a['value_arcsec']:+.2f} ± {a['U_arcsec']:.2f}″"
                          for a in doc[table]["angles"])
        lines.append(f"  {table.replace('_', ' ')}: {cells}")
    return "\n".join(lines)


def coning_table(sensors, units: str = "V") -> Table:
    table = rich_table.Table(
        title="Coning model (Tripp eq. 2): v = b + S·(u·g), ± u (k=1)", box=box.SIMPLE_HEAD, pad_edge=False
    )
    for col in ("sensor", f"b ({units})", f"S ({units}/g)", "Ω (°)", "Ω 95 % interval (°)", "A (°)"):
        table.add_column(col, justify="right")
    for c in sensors:
        d = c.to_json()
        se = d["standard_errors"]
        azimuth = (
            console.with_standard_error(d["azimuth_deg"], se["azimuth_deg"])
            if d["azimuth_deg"] is not None
            else "undefined"
        )
        omega = console.with_standard_error(d["omega_deg"], se["omega_deg"])
        low, high = d["omega_interval_95_deg"]
        table.add_row(
            c.name,
            console.with_standard_error(d["b"], se["b"]),
            console.with_standard_error(d["S"], se["S"]),
            omega if d["omega_interval_reliable"] else f"{omega} *",
            f"{low:.3g} … {high:.3g}",
            azimuth,
        )
    if not all(c.azimuth_defined for c in sensors):
        table.caption = f"* {analysis_coning.OMEGA_NEAR_ZERO}"
    return table


def replication_table(rep: dict, units: str = "V", sigma_e: list[float] | None = None) -> Table:
    """Tripp & Tcheng Table 2's columns per sensor: σ_E, σ_bias, σ_prec; the bias test T_bias against
    its 95 % limit F_bias; the offset and sensitivity drifts σ_b, σ_S and their tests T_b, T_S against
    their 95 % limit F_bS."""
    table = rich_table.Table(title="Replicated calibration (Tripp Table 2)")
    for col in ("sensor", f"σ_E ({units})", f"σ_bias ({units})", f"σ_prec ({units})", "T_bias (df)",
                "(F_bias)95", f"σ_b ({units})", f"σ_S ({units}/g)", "T_b", "T_S", "(F_bS)95"):
        table.add_column(col, justify="right")
    for j, (sensor, r) in enumerate(rep.items()):
        lof, off, sens = r["lack_of_fit"], r["drift"].get("offset"), r["drift"].get("sensitivity")

        def statistic(t) -> str:  # None or NaN: undefined (no pure error to test against)
            f = t["F"]
            return "undefined" if f is None or f != f else f"{f:.3g}{' *' if t['significant'] else ''}"

        def flag(t):
            return "—" if t is None else statistic(t)

        def size(t):
            return "—" if t is None or t.get("sigma_drift") is None else f"{t['sigma_drift']:.3g}"
        table.add_row(sensor, "—" if sigma_e is None else f"{sigma_e[j]:.3g}", f"{r['sigma_bias']:.3g}",
                      f"{r['sigma_prec']:.3g}", f"{statistic(lof)} ({lof['df'][0]}, {lof['df'][1]})",
                      f"{lof['critical_95']:.3g}", size(off), size(sens), flag(off), flag(sens),
                      "—" if off is None else f"{off['critical_95']:.3g}")
    table.caption = ("* significant at 5 %; undefined: no pure error (noise-free readings). σ_bias is the "
                     "standard deviation of a point's bias (labcal's convention; Table 2's is √ of its share "
                     "of σ_E²)")
    return table


def _units(text: str) -> str:
    try:
        return readings_csv.unit_named(text, "--units")
    except LabcalError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--units: ")) from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help=summary("fit"),
                       description="Least-squares fit of V = B + gᵀS on the nominal gravity "
                                   "(Soto eqs. 13–21) with standard errors, full covariance, replicated-"
                                   "calibration analysis (Tripp & Tcheng §8) and, on request, the coning "
                                   "model and intervals.")
    p.add_argument("readings", help="readings CSV (replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz)")
    p.add_argument("--model", choices=["linear", "coning", "device"], default=None,
                   help="linear: Soto's X; coning: per sensor b, S, Ω, A (Tripp eq. 2); device: X together "
                        "with the calibration device's misalignments a, b, d, e, f, k (default: device when "
                        "the plan identifies all six, else linear; a note says which and why)")
    p.add_argument("--extend", metavar="NAMES",
                   help=f"extra regressors, comma-separated: {', '.join(EXTENSION_NAMES)}")
    p.add_argument("--index-errors", action="store_true",
                   help="device model: also estimate each visited pitch and roll angle's index error "
                        "(zero mean per table, where identifiable) with its F test against the device model")
    p.add_argument("--table-index", type=bounded(float, 0, 3600), default=0.0, metavar="ARCSEC",
                   help="device model: the tables' index accuracy, ± arcseconds at every table angle "
                        "(station file's pitch_index/roll_index), propagated into the misalignments' and "
                        "coefficients' uncertainty")
    p.add_argument("--table-wobble", type=bounded(float, 0, 3600), default=0.0, metavar="ARCSEC",
                   help="device model: the tables' wobble, ± arcseconds at every table angle")
    p.add_argument("--test-extensions", action="store_true",
                   help="F test whether each extension is warranted")
    p.add_argument("--at", action="append", metavar="PITCH,ROLL[,Y,U]",
                   help="predicted output with confidence and prediction intervals here (repeatable)")
    p.add_argument("--level", type=bounded(float, 0, 1, lo_open=True, hi_open=True), default=0.95,
                   help="interval level, 0 < LEVEL < 1 (default %(default)s)")
    p.add_argument("--allow-outliers", action="store_true",
                   help="exit 0 even when readings fail the gross-error checks (they are still listed)")
    p.add_argument("--units", type=_units, metavar="V|mV|counts|m/s2",
                   help="the outputs' unit (default: what the readings file states, else V); B is then in "
                        "it and S per g in it, and only volts are held to a DMM's range")
    p.add_argument("--station", metavar="FILE",
                   help="also hold the residual to what this station file declares: its [sequencer.settle] "
                        "noise_v and samples, its [uncertainty] table index and wobble (a χ² test at a 1 %% "
                        "false-alarm rate, with the readings it cannot explain named)")
    p.add_argument("--json", action="store_true", help="print the fit as JSON on stdout")
    p.set_defaults(func=cmd_fit)
