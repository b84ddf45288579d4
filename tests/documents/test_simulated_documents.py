"""Simulated stays simulated: a dry run's certificate.json, report (HTML and PDF)
and DCC say so first; its budget lists the simulator's own error sources at the sizes the rig applies
them; `certificate approve` refuses it (tests/documents/test_approvers.py shows the one line)."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from pypdf import PdfReader
from simulated_runs import simulated_run

from labcal.app.run_documents import write_run_outputs
from labcal.config.emulation import default_instrument
from labcal.documents.certificate import read_certificate

DATA = Path(__file__).parent.parent / "data" / "dcc"
DCC_NS = "{https://ptb.de/dcc}"
INDEX, WOBBLE, MOUNT_SD = 3.0, 1.5, 1.0  # arcsec: this test's rig, not the default one


@pytest.fixture(scope="module")
def dry(tmp_path_factory):
    """A dry run under a real-looking serial on a rig with known index error, wobble and seating
    scatter, and its documents."""
    base = tmp_path_factory.mktemp("dry")
    rig = base / "rig.toml"
    rig.write_text(f"[device]\nindex_arcsec = {INDEX}\nwobble_arcsec = {WOBBLE}\n"
                   f"mount_repeat_arcsec = {MOUNT_SD}\n")
    run_dir = simulated_run(base / "run", base / "lab.sqlite", seed=3, rig=rig, plan="one-mount-16",
                            serial="ACC-0042", report=False)  # its documents written just below
    write_run_outputs(run_dir, db=base / "lab.sqlite")
    return run_dir


def test_certificate_json_says_simulated_on_its_first_line(dry):
    first = (dry / "certificate.json").read_text().splitlines()[1]  # line 0 is "{"
    assert first.startswith('  "notice": "SIMULATED: ')
    cert = read_certificate(dry / "certificate.json")
    assert cert.statements[0] == cert.notice and cert.instrument.serial == "ACC-0042"


def test_report_html_and_every_pdf_page_say_simulated_first(dry):
    html = (dry / "report.html").read_text()
    body = html.split("<body>", 1)[1].lstrip()
    assert body.startswith('<p class="verdict fail-v">SIMULATED: ')
    assert "<title>SIMULATED — " in html
    pages = [page.extract_text() for page in PdfReader(dry / "report.pdf").pages]
    assert len(pages) >= 5
    for page in pages:  # the header of a text page, the caption of a figure page
        assert "SIMULATED — " in page
    assert pages[0].lstrip().startswith("SIMULATED — Calibration certificate")


def test_the_dcc_states_it_in_its_first_statement_and_validates(dry):
    import xmlschema

    path = dry / "certificate.dcc.xml"
    xmlschema.XMLSchema(str(DATA / "dcc.xsd")).validate(str(path))  # the tests' own copy of PTB's schema
    assert path.read_text(encoding="utf-8").splitlines()[1].startswith("<!-- SIMULATED: ")
    statements = ET.parse(path).getroot().find(f"{DCC_NS}administrativeData/{DCC_NS}statements")
    first = statements.findall(f"{DCC_NS}statement")[0]
    assert first.get("refType") == "labcal_simulatedData"
    assert first.find(f"{DCC_NS}declaration/{DCC_NS}content").text.startswith("SIMULATED: ")


def test_the_dry_run_budget_lists_the_simulators_sources_at_their_sizes(dry):
    budget = read_certificate(dry / "certificate.json").uncertainty_budget
    rows = {r.source: r for r in budget.rows}
    # the rig's index errors and wobble are bounded by their amplitudes: rectangular half-widths
    for source, half in (("pitch table index accuracy", INDEX), ("roll table index accuracy", INDEX),
                         ("pitch table wobble", WOBBLE), ("roll table wobble", WOBBLE)):
        assert rows[source].standard_uncertainty == pytest.approx(half / math.sqrt(3), rel=1e-12)
        assert rows[source].pitch_rms_arcsec > 0 or rows[source].roll_rms_arcsec > 0
    # the seating scatter is normal with σ per angle: u = σ
    assert rows["mount repeatability"].standard_uncertainty == pytest.approx(MOUNT_SD, rel=1e-12)
    # the instrument's noise, per reading averaged over the sequencer's 10 samples, shown not added
    noise = default_instrument().noise_v / math.sqrt(10)
    assert rows["DMM noise"].standard_uncertainty == pytest.approx(noise, rel=1e-12)
    assert not rows["DMM noise"].added
    inputs = budget.inputs
    assert inputs.bias_tempco_v_per_k == pytest.approx(max(map(abs, default_instrument().tc_bias_v_per_c)))
    assert inputs.dmm_reading == 0 and inputs.dmm_range_v == 0  # the simulated DMM reads exactly


def test_a_real_station_keeps_its_own_inputs(tmp_path):
    """The simulator's inputs are a dry run's only: a station of real devices keeps its file's."""
    from labcal.config.snapshot import parse_snapshot
    from labcal.config.station import CertificateSection
    from labcal.documents.simulated import with_simulator_inputs

    section = CertificateSection()
    station = parse_snapshot(json.dumps({"kind": "station", "station": {}, "emulate": False}))
    assert with_simulator_inputs(section, station, None) is section


def test_the_dcc_states_sensitivities_per_metre_per_second_squared(dry):
    """Issue 23 item 6: sensitivities are volts per g, and D-SI has no g. PTB's own D-SI parser
    (dsiunits, a second library) reads every unit the DCC states; the sensitivities are V/(m s⁻²),
    the values S/g_n with g_n = 9.80665 m s⁻² (standard gravity, 3rd CGPM 1901), the covariance
    scaled alike, the bias still in volts."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from dsi_unit import DsiUnit

    g_n = 9.80665
    cert = read_certificate(dry / "certificate.json")
    root = ET.parse(dry / "certificate.dcc.xml").getroot()
    si = "{https://ptb.de/si}"
    lists = root.findall(f".//{si}realList")
    assert len(lists) == 3
    volt, per_acceleration = DsiUnit(r"\volt"), DsiUnit(r"\volt") / DsiUnit(r"\metre\second\tothe{-2}")
    for j, values in enumerate(lists):
        reals = values.findall(f"{si}real")
        for i, real in enumerate(reals):
            unit = DsiUnit(real.find(f"{si}unit").text)
            assert unit.valid
            scale = 1.0 if i == 0 else 1 / g_n
            assert unit == (volt if i == 0 else per_acceleration)
            value = float(real.find(f"{si}value").text)
            assert value == pytest.approx(cert.coefficients[i, j] * scale, rel=1e-15)
            U = float(real.find(f"{si}expandedUnc/{si}uncertainty").text)
            assert U == pytest.approx(cert.U[i, j] * scale, rel=1e-15)
        columns = values.findall(f"{si}ellipsoidalRegion/{si}covarianceMatrix/{si}column")
        for c, column in enumerate(columns):
            for r, cov in enumerate(column.findall(f"{si}covariance")):
                unit = DsiUnit(cov.find(f"{si}unit").text)
                assert unit.valid
                expected_unit = (DsiUnit(r"\volt") if r == 0 else per_acceleration) * \
                    (DsiUnit(r"\volt") if c == 0 else per_acceleration)
                assert unit == expected_unit
                scale = (1.0 if r == 0 else 1 / g_n) * (1.0 if c == 0 else 1 / g_n)
                complete = cert.coefficient_covariance()[3 * r + j, 3 * c + j]  # the one U comes from
                assert float(cov.find(f"{si}value").text) == pytest.approx(complete * scale, rel=1e-15,
                                                                           abs=1e-300)
    text = (dry / "certificate.dcc.xml").read_text(encoding="utf-8")
    assert "g_n = 9.80665 m s⁻²" in text and 'refType="labcal_sensitivityUnit"' in text
