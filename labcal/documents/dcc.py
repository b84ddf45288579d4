"""The Digital Calibration Certificate: `certificate.dcc.xml` beside the JSON, in PTB's DCC 3.2.0
schema with D-SI 2.1.0 units, validated against the schema when it is written.

Every coefficient is an `si:real` with its expanded uncertainty, coverage factor and probability;
each sensor's four coefficients form an `si:realList` whose `si:ellipsoidalRegion` carries their
4×4 covariance. The inputs are gravity normalised to 1 g, so the fit's sensitivities are volts per g;
D-SI has no g, so the DCC states them in \\volt\\metre\\tothe{-1}\\second\\tothe{2} (V per m s⁻²)
through the standard acceleration of gravity (`STANDARD_GRAVITY`), and says so in a statement; the
bias is in \\volt. The attitude U95 of the usage envelope is in \\degree. The administrative
data are the certificate's (ISO/IEC 17025 §7.8.2.1), its statements in ``dcc:statements``; a dry
run's first statement (``refType`` labcal_simulatedData, and a comment before the root element) says
its data are simulated. The schemas ship with labcal
(`dcc_schema/`), so validation never needs the network. Validation is libxml2's (lxml), a complete
XSD 1.0 validator that compiles the schema in milliseconds where xmlschema took most of a second on
every issue; the tests check the documents with xmlschema against their own copy of the schema, so
two validators written by others agree on every DCC labcal issues.
"""

from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np
from lxml import etree

from labcal.analysis.fit import ROW_NAMES
from labcal.config.files import write_atomic
from labcal.documents.certificate import Certificate
from labcal.errors import LabcalError

DCC = "https://ptb.de/dcc"
SI = "https://ptb.de/si"
SCHEMA_VERSION = "3.2.0"
DCC_FILE = "certificate.dcc.xml"
# D-SI has no unit g. Gravity is normalised to 1 g in the fit, so S is in volts per g; the DCC states
# it per m s⁻² through the standard acceleration of gravity g_n = 9.80665 m s⁻² (exact, by convention:
# 3rd CGPM, 1901), a documented quotient: S_SI = S / g_n, U and covariance scaled alike. The bias row
# stays in the instrument's output unit (volts unless its station says otherwise).
STANDARD_GRAVITY = 9.80665
PER_UNIT = np.array([1.0, 1 / STANDARD_GRAVITY, 1 / STANDARD_GRAVITY, 1 / STANDARD_GRAVITY])
# D-SI spellings per output unit (the station's [instrument] units): the bias, the sensitivity per
# m s⁻², and the covariances of (bias, bias), (bias, sensitivity), (sensitivity, sensitivity).
# Counts are dimensionless (\\one); m/s² per m s⁻² is too.
DSI_UNITS: dict[str, tuple[str, tuple[str, str, str, str], tuple[str, str, str]]] = {
    "V": ("V", ("\\volt",) + ("\\volt\\metre\\tothe{-1}\\second\\tothe{2}",) * 3,
          ("\\volt\\tothe{2}", "\\volt\\tothe{2}\\metre\\tothe{-1}\\second\\tothe{2}",
           "\\volt\\tothe{2}\\metre\\tothe{-2}\\second\\tothe{4}")),
    "mV": ("mV", ("\\milli\\volt",) + ("\\milli\\volt\\metre\\tothe{-1}\\second\\tothe{2}",) * 3,
           ("\\milli\\volt\\tothe{2}", "\\milli\\volt\\tothe{2}\\metre\\tothe{-1}\\second\\tothe{2}",
            "\\milli\\volt\\tothe{2}\\metre\\tothe{-2}\\second\\tothe{4}")),
    "counts": ("counts", ("\\one",) + ("\\metre\\tothe{-1}\\second\\tothe{2}",) * 3,
               ("\\one", "\\metre\\tothe{-1}\\second\\tothe{2}", "\\metre\\tothe{-2}\\second\\tothe{4}")),
    "m/s2": ("m s⁻²", ("\\metre\\second\\tothe{-2}",) + ("\\one",) * 3,
             ("\\metre\\tothe{2}\\second\\tothe{-4}", "\\metre\\second\\tothe{-2}", "\\one")),
}
UNIT = DSI_UNITS["V"][1]
COVARIANCE_UNIT = DSI_UNITS["V"][2]


def sensitivity_statement(unit: str = "V") -> str:
    """How the sensitivities are stated, in the instrument's output ``unit`` (V: volts)."""
    spoken = DSI_UNITS[unit][0]
    per_g = "volts" if unit == "V" else spoken
    return ("Sensitivities are fitted against gravity normalised to 1 g (the local gravity at the "
            "calibration, whose value cancels in attitude) and are stated in "
            f"{spoken}/(m s⁻²) as S/g_n with the standard acceleration of gravity g_n = "
            f"{STANDARD_GRAVITY!r} m s⁻² (3rd CGPM, 1901): multiply by g_n for {per_g} per g. They are the "
            "response to the direction of gravity, not a calibration of the response to an acceleration of "
            "a given magnitude in m s⁻².")


SENSITIVITY_STATEMENT = sensitivity_statement()
SIMULATED_REF_TYPE = "labcal_simulatedData"  # dcc:statement/@refType of a dry run's notice
UNKNOWN_COUNTRY = "ZZ"  # ISO 3166 user-assigned: the lab file states no country_code
ET.register_namespace("dcc", DCC)
ET.register_namespace("si", SI)


def _d(parent: ET.Element, tag: str, text: str | None = None) -> ET.Element:
    element = ET.SubElement(parent, f"{{{DCC}}}{tag}")
    if text is not None:
        element.text = text
    return element


def _s(parent: ET.Element, tag: str, text: str | None = None) -> ET.Element:
    element = ET.SubElement(parent, f"{{{SI}}}{tag}")
    if text is not None:
        element.text = text
    return element


def _text(parent: ET.Element, tag: str, text: str) -> ET.Element:
    """A dcc:textType element: its words in dcc:content."""
    element = _d(parent, tag)
    _d(element, "content", text or "not stated")
    return element


def _number(x: float) -> str:
    return repr(float(x))


def _expanded(parent: ET.Element, U: float, k: float) -> None:
    unc = _s(parent, "expandedUnc")
    _s(unc, "uncertainty", _number(U))
    _s(unc, "coverageFactor", _number(k))
    _s(unc, "coverageProbability", "0.95")


def _administrative(root: ET.Element, cert: Certificate) -> None:
    a = cert.administration
    admin = _d(root, "administrativeData")
    software = _d(_d(admin, "dccSoftware"), "software")
    _text(software, "name", "labcal")
    _d(software, "release", cert.labcal_version)
    core = _d(admin, "coreData")
    _d(core, "countryCodeISO3166_1", (a.laboratory.country_code if a else "") or UNKNOWN_COUNTRY)
    _d(core, "usedLangCodeISO639_1", "en")
    _d(core, "mandatoryLangCodeISO639_1", "en")
    _d(core, "uniqueIdentifier", cert.number)
    if a is not None and a.item.received is not None:
        _d(core, "receiptDate", a.item.received.isoformat())
    _d(core, "beginPerformanceDate", cert.calibrated_utc.date().isoformat())
    _d(core, "endPerformanceDate", (cert.completed_utc or cert.calibrated_utc).date().isoformat())
    _d(core, "performanceLocation", "laboratory")
    _d(core, "issueDate", cert.issued_utc.date().isoformat())
    item = _d(_d(admin, "items"), "item")
    _text(item, "name", "three-axis accelerometer attitude instrument" if cert.package is None else
          f"{cert.package.package} accelerometer attitude sensor package (sensors {', '.join(cert.sensors)})")
    _text(_d(item, "manufacturer"), "name", a.item.manufacturer if a else "")
    if a is not None and a.item.model:
        _d(item, "model", a.item.model)
    identification = _d(_d(item, "identifications"), "identification")
    _d(identification, "issuer", "manufacturer")
    _d(identification, "value", cert.instrument.serial)
    _text(identification, "name", "serial number")
    lab = _d(_d(admin, "calibrationLaboratory"), "contact")
    _text(lab, "name", a.laboratory.name if a else cert.laboratory)
    _text(_d(lab, "location"), "further", (a.laboratory.address if a else "") or "not stated")
    person = _d(_d(admin, "respPersons"), "respPerson")
    approval = cert.approval
    _text(_d(person, "person"), "name", approval.by if approval else "not approved (DRAFT)")
    if approval is not None:
        _d(person, "role", approval.role)
        _d(person, "mainSigner", "true")
    customer = _d(admin, "customer")
    _text(customer, "name", (a.customer if a else None) or "not stated")
    _text(_d(customer, "location"), "further", "not stated")
    statements = _d(admin, "statements")
    if cert.notice:  # the first statement of a dry run's DCC says its data are simulated
        statement = _d(statements, "statement", None)
        statement.set("refType", SIMULATED_REF_TYPE)
        _text(statement, "name", "Simulated data")
        _text(statement, "declaration", cert.notice)
    for text in cert.statements:
        if text != cert.notice:
            _text(_d(statements, "statement"), "declaration", text)
    unit = _d(statements, "statement")
    unit.set("refType", "labcal_sensitivityUnit")
    _text(unit, "declaration", sensitivity_statement(cert.output_unit))


def _results(root: ET.Element, cert: Certificate) -> None:
    result = _d(_d(root, "measurementResults"), "measurementResult")
    _text(result, "name", "Calibration coefficients X = [Bᵀ; S] and attitude uncertainty")
    method = _d(_d(result, "usedMethods"), "usedMethod")
    _text(method, "name", f"plan {cert.plan.name} (sha256 {cert.plan.sha256})")
    _text(method, "description", cert.method)
    _d(method, "reference", "Soto 2020 (linear model, eqs. 13–21); Tripp & Tcheng 1999 (statistics)")
    results = _d(result, "results")
    X, U = cert.coefficients, cert.U
    k = cert.expanded_uncertainty.k
    spoken, units, covariance_units = DSI_UNITS[cert.output_unit]
    for j, sensor in enumerate(cert.sensors):
        entry = _d(results, "result")
        _text(entry, "name", f"sensor {sensor}: bias ({spoken}) and sensitivity to the acceleration "
                             f"components a_x, a_y, a_z ({spoken} per m s⁻², fitted per g and stated per "
                             f"standard gravity g_n = {STANDARD_GRAVITY!r} m s⁻²)")
        values = _s(_s(_d(_d(entry, "data"), "quantity"), "list"), "realList")
        for i, row in enumerate(ROW_NAMES):
            real = _s(values, "real")
            _s(real, "label", f"{row}_{sensor}")
            _s(real, "value", _number(X[i, j] * PER_UNIT[i]))
            _s(real, "unit", units[i])
            _expanded(real, U[i, j] * PER_UNIT[i], k[j])
        # the complete covariance (Type A and B) that U above comes from, not the fit's Type A alone
        idx = np.arange(4) * len(cert.sensors) + j
        covariance = cert.coefficient_covariance()[np.ix_(idx, idx)] * np.outer(PER_UNIT, PER_UNIT)
        region = _s(values, "ellipsoidalRegion")
        matrix = _s(region, "covarianceMatrix")
        for c, column in enumerate(covariance.T):
            col = _s(matrix, "column")
            for r, value in enumerate(column):
                cov = _s(col, "covariance")
                _s(cov, "value", _number(value))
                _s(cov, "unit", covariance_units[min(r, 1) + min(c, 1)])
        _s(region, "coverageFactor", _number(k[j]))
        _s(region, "coverageProbability", "0.95")
    for total in cert.uncertainty_budget.totals if cert.uncertainty_budget else []:
        entry = _d(results, "result")
        _text(entry, "name", f"expanded uncertainty of inferred {total.angle}, largest over the usage "
                             "envelope" if cert.package is None else
              f"expanded uncertainty of inferred {total.angle}, largest over the region the package section "
              f"states ({cert.package.statement})")
        real = _s(_d(_d(entry, "data"), "quantity"), "real")
        _s(real, "label", f"U95 {total.angle}")
        _s(real, "value", _number(total.U95_arcsec / 3600))
        _s(real, "unit", "\\degree")


def dcc_document(cert: Certificate) -> bytes:
    root = ET.Element(f"{{{DCC}}}digitalCalibrationCertificate", {"schemaVersion": SCHEMA_VERSION})
    _administrative(root, cert)
    _results(root, cert)
    ET.indent(root)
    document = ET.tostring(root, encoding="utf-8", xml_declaration=True)
    if cert.notice:  # said before the document too, where a reader of the file looks first
        declaration, rest = document.split(b"\n", 1)
        document = declaration + b"\n<!-- " + cert.notice.encode("utf-8") + b" -->\n" + rest
    return document


@cache
def schema() -> etree.XMLSchema:
    """PTB's DCC schema, from the copy shipped with labcal (compiled once per process)."""
    with resources.as_file(resources.files("labcal.documents") / "dcc_schema" / "dcc.xsd") as path:
        return etree.XMLSchema(etree.parse(str(path), etree.XMLParser(no_network=True)))


def validation_error(document: bytes) -> str | None:
    """Why the document is not a valid DCC (the first reason, one line), or None."""
    try:
        root = etree.fromstring(document, etree.XMLParser(resolve_entities=False, no_network=True))
    except etree.XMLSyntaxError as exc:
        return f"not well-formed XML: {exc}".replace("\n", " ")
    validator = schema()
    if validator.validate(root):
        return None
    error = validator.error_log[0]
    return f"{error.message} at {error.path} (line {error.line})".replace("\n", " ")


def write_dcc(path: Path, cert: Certificate) -> Path:
    """Write certificate.dcc.xml after validating it; an invalid one is one line and not written."""
    document = dcc_document(cert)
    why = validation_error(document)
    if why is not None:
        raise LabcalError(f"{path}: the Digital Calibration Certificate fails PTB's DCC {SCHEMA_VERSION} "
                          f"schema ({why}); nothing was written — report this with the run directory")
    signed = cert.approval.dcc_sha256 if cert.approval else None
    if signed is not None and hashlib.sha256(document).hexdigest() != signed:
        raise LabcalError(f"{path}: the DCC made of the approved certificate is not the one its approver "
                          "signed (another labcal?); nothing was written — approve it again")
    return write_atomic(path, document)
