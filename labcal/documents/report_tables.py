"""The report's tables: what the certificate states, built once from its model and rendered three
ways — HTML (`labcal.documents.report_html`), PDF (`labcal.documents.report_pdf`) and the terminal
(`labcal.commands.report`) — so that every output says the same thing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime

from labcal.analysis.fit import ROW_NAMES
from labcal.config.dates import written_date, written_time_utc
from labcal.config.uncertainty import overdue_standards as overdue
from labcal.documents.certificate import Certificate, format_result, format_uncertainty
from labcal.documents.certificate_sections import Replication

SIMULATED_WORD = "SIMULATED"  # heads every page of a dry run's report (its notice says why)
UNITS = ("V", "V/g", "V/g", "V/g")


@dataclass(frozen=True)
class Table:
    title: str
    header: list[str]
    rows: list[list[str]]
    caption: str = ""
    emphasis: set[tuple[int, int]] = field(default_factory=set)  # (row, column) cells that fail


def _g(x: float | None, spec: str = ".3g") -> str:
    return "—" if x is None else format(x, spec)


def identification_table(cert: Certificate) -> Table:
    env, plan, data = cert.environment, cert.plan, cert.data
    temperature = ("not recorded" if env.temperature_c_min is None else
                   f"{env.temperature_c_min:.2f} … {env.temperature_c_max:.2f} °C "
                   f"(mean {env.temperature_c_mean:.2f} °C)")
    rows = [
        ["certificate", cert.certificate_id],
        ["laboratory", cert.laboratory or "not stated"],
        ["instrument serial", cert.instrument.serial + (f" ({cert.instrument.description})"
                                                        if cert.instrument.description else "")],
        ["calibration device", cert.station.description + (" (simulated: a dry run, not a calibration "
                                                           "of a real instrument)" if cert.station.simulated
                                                           else "")],
        ["operator", cert.operator or "not recorded"],
        ["calibrated", written_time_utc(cert.calibrated_utc)],
        ["issued", written_time_utc(cert.issued_utc)],
        ["plan", f"{plan.name}: {len(plan.points)} points × {len(plan.mounts)} mount(s) × "
                 f"{plan.replicates} replicate(s); sha256 {plan.sha256[:16]}…"],
        ["readings", f"{data.n_points} points in {data.replicates} replicate(s); sha256 "
                     f"{data.readings_sha256[:16]}…"],
        ["temperature", temperature],
        ["software", f"labcal {cert.labcal_version}"],
    ]
    rows[0] = ["certificate", cert.number + (f", replacing {cert.replaces}" if cert.replaces else "")]
    a = cert.administration
    if a is not None:
        lab = ", ".join(p for p in (a.laboratory.name, a.laboratory.address) if p) or "not stated"
        rows[1] = ["laboratory", lab + (f"; accreditation {a.laboratory.accreditation_id}"
                                        if a.laboratory.accreditation_id else "")]
        item = " ".join(p for p in (a.item.manufacturer, a.item.model) if p)
        rows[2:2] = [["customer", a.customer or "not stated"],
                     ["item", f"{item or 'instrument'}, serial {a.item.serial}; received "
                              f"{written_date(a.item.received) if a.item.received else 'date not recorded'}"]]
        rows += [["equipment", "; ".join(f"{e.role}: {e.description} ({e.reported()})"
                                         for e in a.equipment)],
                 ["traceability", "; ".join(f"{t.equipment} {t.identity}: certificate {t.certificate} "
                                            f"({t.issued_by}), due {written_date(t.due)}"
                                            for t in a.traceability)
                  or "no reference standards recorded (station file [[traceability]])"],
                 ["ambient conditions", a.ambient]]
    rows.append(["approval", status_text(cert)])
    return Table("Identification", ["item", "value"], rows)


def verdict_text(cert: Certificate) -> str:
    if cert.conformity is None:
        return "no statement of conformity: no tolerance was given"
    return "PASS" if cert.conformity.passed else "FAIL"


def conformity_table(cert: Certificate) -> Table:
    c = cert.conformity
    if c is None:
        return Table("Statement of conformity", ["verdict"], [[verdict_text(cert)]],
                     "No tolerance was given for this calibration, so no conformity is stated.")
    rows = [[k.quantity, f"{format_uncertainty(k.value)} {k.unit}", f"{k.limit:g} {k.unit}",
             "pass" if k.passed else "FAIL"] for k in c.checks]
    emphasis = {(i, 3) for i, k in enumerate(c.checks) if not k.passed}
    return Table(f"Statement of conformity: {verdict_text(cert)}", ["quantity", "value", "limit", "result"],
                 rows, f"Decision rule: {c.decision_rule}", emphasis)


def attitude_table(cert: Certificate) -> Table:
    a = cert.attitude
    def where(at): return "—" if at is None else f"pitch {at[0]:g}°, roll {at[1]:g}°"
    def deg(u): return "undefined" if u is None else f"{format_uncertainty(u)}°"
    rows = [["pitch", deg(a.pitch_U95_max_deg), where(a.pitch_U95_max_at_deg), deg(a.pitch_U95_rms_deg)],
            ["roll", deg(a.roll_U95_max_deg), where(a.roll_U95_max_at_deg), deg(a.roll_U95_rms_deg)]]
    cf = a.closed_form
    if cf is not None:
        rows += [["pitch, closed form", deg(cf.pitch_U95_max_deg), where(cf.pitch_U95_max_at_deg),
                  deg(cf.pitch_U95_rms_deg)],
                 ["roll, closed form", deg(cf.roll_U95_max_deg), where(cf.roll_U95_max_at_deg),
                  deg(cf.roll_U95_rms_deg)]]
    (p0, p1), (r0, r1) = a.usage_pitch_deg, a.usage_roll_deg
    caption = (f"Over pitch {p0:g}…{p1:g}° × roll {r0:g}…{r1:g}° in {a.grid_step_deg:g}° steps "
               f"({a.grid_points} attitudes); "
               f"{a.method}; k = {a.k:.2f}.")
    if a.roll_undefined_points:
        caption += f" Roll is undefined at {a.roll_undefined_points} attitude(s) near pitch ±90°."
    if cf is not None:
        caption += f" {cf.statement}"
    return Table("Attitude uncertainty (95 %) over the usage envelope", ["angle", "largest U95", "at",
                                                                          "RMS of U95"], rows, caption)


def coefficients_with_expanded_uncertainty(cert: Certificate) -> Table:
    """The certified coefficients ± U95 (the terminal's fit table,
    `labcal.commands.console.coefficients_with_standard_errors`, states ± one standard error)."""
    X, U = cert.coefficients, cert.U
    e = cert.expanded_uncertainty
    output = cert.output_unit
    units = UNITS if output == "V" else (output, *[f"{output}/g"] * 3)
    rows = [[f"{name} ({unit})", *(format_result(X[i, j], U[i, j]) for j in range(len(cert.sensors)))]
            for i, (name, unit) in enumerate(zip(ROW_NAMES, units, strict=True))]
    rows.append([f"S_E ({output})", *(format_uncertainty(s) for s in cert.fit.residual_standard_error)])
    rows.append(["k", *(f"{k:.2f}" for k in e.k)])
    rows.append(["ν_eff", *(str(n) for n in e.nu_eff)])
    rows.append(["basis of u", *cert.fit.uncertainty_basis])
    return Table("Coefficients X = [Bᵀ; S] with expanded uncertainty (y ± U)",
                 ["coefficient", *(f"sensor {s}" for s in cert.sensors)], rows, e.statement)


def package_table(cert: Certificate) -> Table:
    """A package's sensors in Tripp & Tcheng's terms (eq. 8) and how its angles are obtained in use."""
    p = cert.package
    assert p is not None
    rows = [[f"sensor {axis}", f"{c.b:.6g}", f"{c.S:.6g}", f"{c.omega_deg:.4g}", f"{c.azimuth_deg:.4g}"]
            for axis, c in p.coefficients.items()]
    return Table(f"The {p.package} package (Tripp & Tcheng §6; {p.equations})",
                 ["sensor", f"b ({cert.output_unit})", f"S ({cert.output_unit}/g)", "Ω (°)", "A (°)"], rows,
                 p.statement)


def replication_table(cert: Certificate) -> Table:
    rep = cert.fit.replication
    header = ["sensor", "σ_prec (V)", "σ_bias (V)", "lack of fit F (df)", "F crit 95 %", "p",
              "offset drift F (p)", "sensitivity drift F (p)"]
    if rep is None:
        return Table("Replication and lack of fit (Tripp & Tcheng Table 2)", ["analysis"],
                     [["not available: one replicate"]], "Precision and bias cannot be separated and drift "
                     "cannot be tested without replicates.")
    rows, emphasis = [], set()
    for i, (sensor, r) in enumerate(rep.items()):
        lof = r.lack_of_fit

        def drift(name: str, col: int, r: Replication = r, i: int = i) -> str:
            t = r.drift.get(name)
            if t is None:
                return "—"
            if t.significant:
                emphasis.add((i, col))
            return f"{t.F:.3g} ({t.p_value:.2g})"
        if lof.significant:
            emphasis.add((i, 3))
        rows.append([sensor, _g(r.sigma_prec), _g(r.sigma_bias), f"{lof.F:.3g} {tuple(lof.df)}",
                     f"{lof.critical_95:.3g}", f"{lof.p_value:.2g}", drift("offset", 6),
                     drift("sensitivity", 7)])
    first = next(iter(rep.values()))
    return Table("Replication and lack of fit (Tripp & Tcheng Table 2)", header, rows,
                 f"{first.distinct_points} distinct points × {first.replicates} replicates; "
                 "highlighted: significant at 5 %.", emphasis)


def audit_table(cert: Certificate) -> Table:
    a = cert.plan_audit
    rows = [[name, f"{m.bias_max:.2e}", f"{m.off_diagonal_max:.2e}", f"{m.diagonal_max:.2e}",
             "yes" if m.cancelled else "no"] for name, m in a.misalignments.items()]
    return Table("Plan audit: leakage of calibration-device misalignments (Soto §7)",
                 ["misalignment", "max |∂B| per rad", "max |∂S off-diag.| per rad", "max |∂S diag.| per rad",
                  "cancelled in B and off-diag. S"], rows,
                 f"First-order change of the coefficients of an ideal instrument (B = 0, S = I) per radian "
                 f"of each misalignment; zero below {a.zero_below:g}. Box figure of merit over the usage "
                 f"pitch range: V_R^½ = {a.figure_of_merit_usage_sqrt:.4f}.")


def _arcsec(x: float | None) -> str:
    """Arcseconds to three digits; rounding noise (what a plan cancels exactly) shows as 0."""
    return "—" if x is None else "0" if abs(x) < 1e-9 else f"{x:.3g}"


def budget_table(cert: Certificate) -> Table:
    """The GUM budget: one row per source, its contribution u_i to pitch and roll (arcsec) at the
    envelope's worst point and RMS over the envelope, then the totals (and the Monte Carlo check)."""
    b = cert.uncertainty_budget
    header = ["source", "type", "distribution", "u (own unit)", "c pitch (″/unit)", "pitch u_i worst (″)",
              "pitch u_i RMS (″)", "c roll (″/unit)", "roll u_i worst (″)", "roll u_i RMS (″)", "ν"]
    if b is None:
        return Table("Uncertainty budget", ["budget"], [["not in this certificate (issued before budgets)"]])
    rows = []
    for r in b.rows:
        name = r.source if r.added else f"{r.source} (not added)"
        rows.append([name, r.type, r.distribution, f"{r.standard_uncertainty:.3g} {r.unit}",
                     _arcsec(r.sensitivity_pitch), _arcsec(r.pitch_worst_arcsec), _arcsec(r.pitch_rms_arcsec),
                     _arcsec(r.sensitivity_roll), _arcsec(r.roll_worst_arcsec), _arcsec(r.roll_rms_arcsec),
                     "∞" if r.degrees_of_freedom is None else f"{r.degrees_of_freedom:.0f}"])
    for t in b.totals:
        rows.append([f"{t.angle}: combined u_c at pitch {t.worst_at_deg[0]:g}°, roll {t.worst_at_deg[1]:g}°",
                     "", "", "", "", f"{t.u_c_arcsec:.3g}", "", "", "", "",
                     "∞" if t.nu_eff is None else f"{t.nu_eff:.0f}"])
        rows.append([f"{t.angle}: U95 = k·u_c (k = {t.k:.2f}); RMS over the envelope {t.U95_rms_arcsec:.3g}″",
                     "", "", "", "", f"{t.U95_arcsec:.3g}", "", "", "", "", ""])
    for c in b.monte_carlo or []:
        rows.append([f"{c.angle}: Monte Carlo U95 ({c.trials} trials, JCGM 101)", "", "", "", "",
                     f"{c.monte_carlo_U95_arcsec:.3g}", "", "", "", "",
                     "agrees" if c.agree_within_5_percent else "differs > 5 %"])
    notes = " ".join(f"{r.source}: {r.note}." for r in b.rows if r.note)
    return Table("Uncertainty budget of inferred pitch and roll (GUM)", header, rows,
                 f"{b.statement} {notes} {b.method}")


def story_table(cert: Certificate) -> Table:
    """The journal's story: faults, retries, wrong mounts, pauses, resumes and the operator's answers."""
    s = cert.story
    title = "What happened during the run (from the journal)"
    if s is None:
        return Table(title, ["events"], [["not in this certificate (issued before the story was recorded)"]])
    rows = [[e.utc.replace("T", " ")[:23], "—" if e.station_time_s is None else f"{e.station_time_s:.1f}",
             e.kind, e.message] for e in s.events]
    emphasis = {(i, 2) for i, e in enumerate(s.events) if e.kind == "fault"}
    counts = ", ".join(f"{n} {kind}" for kind, n in s.counts.items()) or "no events"
    caption = f"{counts}." + (f" {s.omitted} later event(s) not listed; the journal keeps them."
                              if s.omitted else "")
    return Table(title, ["time (UTC)", "rig time (s)", "kind", "what"], rows or [["—", "—", "—", "nothing"]],
                 caption, emphasis)


def overrides_table(cert: Certificate) -> Table:
    """The technician's section: every decision to go on regardless that the run was measured under
    (`labcal.documents.overrides`), with who decided, why and when."""
    found = cert.overrides or []
    rows = [[o.kind, o.what, o.by or "—", o.reason or "—",
             "—" if o.utc is None else written_time_utc(datetime.fromisoformat(o.utc))] for o in found]
    return Table("For the laboratory: overrides the run was measured under",
                 ["override", "what", "by", "reason", "when"], rows,
                 "Each is also stated among the certificate's statements; the journal keeps the record.",
                 {(i, 0) for i in range(len(rows))})


def technician_notes(cert: Certificate) -> Table | None:
    """The technician's section of the HTML report, never on the customer's certificate (the PDF): what
    to run next, with the commands and options (none: nothing to do)."""
    rows = []
    if cert.conformity is None:
        rows.append(["no statement of conformity", "give a tolerance: `labcal report RUN --tolerance-deg "
                     "DEG` (and optionally --bias-max-v V), or a [certificate] section in the station file"])
    if cert.device is not None:
        rows.append(["built on the device model", "`labcal fit RUN/readings.csv --model linear` gives Soto's "
                     "linear fit of the same readings"])
    for line in overdue_standards(cert):
        rows.append(["overdue reference standard", f"{line} Recalibrate it and record the new certificate: "
                     "`labcal standard edit SERIAL --certificate … --calibrated … --due …`"])
    if not rows:
        return None
    return Table("For the laboratory: technician's notes", ["about", "what to do"], rows,
                 "In this report only; the customer's certificate (the PDF) carries no commands.")


def tables(cert: Certificate) -> list[Table]:
    package = [] if cert.package is None else [package_table(cert)]
    return [identification_table(cert), conformity_table(cert), *package, attitude_table(cert),
            budget_table(cert),
            coefficients_with_expanded_uncertainty(cert), replication_table(cert), audit_table(cert),
            story_table(cert), *([overrides_table(cert)] if cert.overrides else [])]


def status_text(cert: Certificate) -> str:
    if cert.approval is None:
        return "DRAFT — not approved"
    a = cert.approval
    return f"approved by {a.by} ({a.role}) on {written_date(a.approved_utc.astimezone(UTC))}"


def overdue_standards(cert: Certificate) -> list[str]:
    """Each reference standard whose calibration was due before this calibration was made: said on
    the certificate's first page, not only in the budget (`labcal station check` says it by the same
    function, `labcal.config.uncertainty.overdue_standards`)."""
    if cert.administration is None:
        return []
    return overdue(cert.administration.traceability, cert.calibrated_utc.date())
