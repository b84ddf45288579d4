"""The approver's desk and the instrument register in Chromium, against `labcal serve` on a real
SQLite lab database: the queue of certificates awaiting approval and what needs attention in each,
a finished run's page with its certificate's own model's residuals, coefficients, U95, verdict and
documents, and after signing who approved it and when; the register of 20 instruments (three due
within 30 days, one overdue), an instrument's page with every calibration, its documents and its
coefficients' drift, and the due page. Every page parses cleanly (html5lib, strict) and has no
WCAG 2.1 A or AA violation that axe-core finds.

The lab: a calibration through the real drivers against `labcal sim serve` (a run that may be
approved), its certificate issued with a tolerance it fails; a four-mount simulated run (a dry run,
certified on the device model); and 20 registered instruments whose earlier calibrations are that
real certificate re-sealed under their serials and dates (each a certificate the history verifies:
schema and digest). What each page must show is set here, from the dates and values the test chose
and the certificate files the runs wrote, never from the functions the pages call.

Set $LABCAL_SCREENSHOTS to a folder to keep a screenshot of each page there
(`tools/desk_screenshots.py` does, for docs/screenshots)."""

from __future__ import annotations

import copy
import json
import os
import uuid
from datetime import UTC, date, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
from lab_server import accessible, add_user, parses_cleanly, served
from simulated_runs import bench_run

from labcal.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("desk_pages")]  # its runs built once, on one worker

INTERVAL = 365
DUE_IN = {"ACC-0103": 5, "ACC-0110": 12, "ACC-0117": 25}  # days until due: within 30 days
OVERDUE = {"ACC-0105": 10}  # days overdue
PASSWORD = "ada's passphrase"
DRIFTED = "ACC-0101"  # two calibrations, B of sensor x moved by 10 mV (U is a few µV)


def _noon(day: date) -> str:
    return datetime(day.year, day.month, day.day, 12, tzinfo=UTC).isoformat()


def _past_certificate(template: dict, serial: str, on: date, n: int, bias_shift_v: float = 0.0):
    """The template certificate as an earlier calibration of ``serial`` on ``on``: its own number, a
    run the lab does not hold, no approval; sealed anew (a digest the history verifies)."""
    from labcal.documents.certificate import seal

    doc = copy.deepcopy(template)
    for key in ("approval", "digest", "revision", "replaces"):
        doc.pop(key, None)
    when = _noon(on)
    doc["certificate_id"] = f"{serial}-{on:%Y%m%d}-{n:04d}"
    doc["instrument"]["serial"] = serial
    doc["calibrated_utc"] = doc["completed_utc"] = doc["issued_utc"] = when
    doc["data"]["journal"]["run_uuid"] = str(uuid.UUID(int=n))
    doc["fit"]["coefficients"][0][0] += bias_shift_v
    return seal(doc)


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    from labcal.documents import history

    base = tmp_path_factory.mktemp("desk")
    db = base / "lab.sqlite"
    bench = bench_run(base / "bench", db, "ACC-0042")  # run 1: real, may be approved
    # its certificate judged against an attitude tolerance of 0.01″ it cannot meet: out of tolerance
    assert main(["report", str(bench), "--tolerance-deg", str(0.01 / 3600), "--db", str(db)]) == 0
    assert main(["run", "--sim", "--yes", "--plan", "four-mount-64", "--serial", "SIM-4M", "--db", str(db),
                 "--out", str(base / "device")]) == 0  # run 2: a dry run on the device model
    template = json.loads((bench / "certificate.json").read_text())
    today = date.today()
    serials = ["ACC-0042"] + [f"ACC-{n:04d}" for n in range(101, 120)]
    for n, serial in enumerate(serials):
        customer = "Northwind Avionics" if n % 2 else "Contoso Flight Test"
        assert main(["instrument", "add", serial, "--model", f"TA-{300 + n % 3}", "--customer", customer,
                     "--location", f"shelf {n % 4 + 1}", "--interval", f"{INTERVAL}d", "--db", str(db)]) == 0
        if serial == "ACC-0042":
            continue  # calibrated today, by the bench run
        left = DUE_IN.get(serial, -OVERDUE.get(serial, 0)) or 60 + 10 * n  # the rest due in 2+ months
        on = today - timedelta(days=INTERVAL - left)
        if serial == DRIFTED:
            history.store(_past_certificate(template, serial, on - timedelta(days=180), 1000 + n), db)
            history.store(_past_certificate(template, serial, on, n, bias_shift_v=0.010), db)
        else:
            history.store(_past_certificate(template, serial, on, n), db)
    assert main(["certificate", "keygen", "--out", str(base / "lab")]) == 0
    assert main(["certificate", "approvers", "add", "ada", "--role", "Technical manager", "--public-key",
                 str(base / "lab.pub"), "--db", str(db)]) == 0
    add_user(str(db), "ada", "approver", PASSWORD)
    add_user(str(db), "vic", "viewer", "vic's passphrase")
    with served(str(db), "--key", str(base / "lab.key")) as url:
        yield {"url": url, "db": db, "bench": bench, "device": base / "device", "serials": serials}


def _signed_in(browser, url: str, name: str = "ada", password: str = PASSWORD):
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page.goto(url + "/login")
    page.fill("input[name=name]", name)
    page.fill("input[name=password]", password)
    page.click("button[type=submit]")
    page.wait_for_url(url + "/")
    return page


def _check(page, url: str, path: str, shot: str | None = None) -> None:
    response = page.goto(url + path)
    assert response is not None and response.status == 200, (path, response and response.status)
    parses_cleanly(response.text(), path)
    accessible(page, path)
    folder = os.environ.get("LABCAL_SCREENSHOTS")
    if folder and shot:
        page.screenshot(path=str(Path(folder) / shot), full_page=True)


def _rows(page, table: str) -> list[str]:
    return page.eval_on_selector_all(f"{table} tbody tr", "rows => rows.map(r => r.dataset.serial)")


def _rx(x):
    c, s = np.cos(x), np.sin(x)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(x):
    c, s = np.cos(x), np.sin(x)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(x):
    c, s = np.cos(x), np.sin(x)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _device_model_residuals(run_dir: Path, cert: dict) -> np.ndarray:
    """Each reading of the run folder's readings.csv less B + gᵀS, with the certificate's B and S and
    the gravity its misalignments give, written out here from Soto eq. 11 and §4's signs (prot[x] =
    Ry(−x), rrot[x] = Rx(x), yrot[x] = Rz(−x); g is row 3 of KM), not through labcal (K×3, V)."""
    rows = np.genfromtxt(run_dir / "readings.csv", delimiter=",", names=True)
    m = {n: np.radians(v["value_arcsec"] / 3600) for n, v in cert["device"]["misalignments"].items()}
    B, S = np.array(cert["fit"]["coefficients"][0]), np.array(cert["fit"]["coefficients"][1:])
    out = []
    for r in rows:
        p, rl, y, u = np.radians([r["pitch_deg"], r["roll_deg"], r["y_deg"], r["u_deg"]])
        km = (_rx(m["b"]) @ _ry(-p) @ _ry(-m["a"]) @ _rz(-m["d"]) @ _rx(rl) @ _rx(m["f"]) @ _ry(-m["e"])
              @ _rz(-m["k"]) @ _rz(-y) @ _rx(u))
        out.append(np.array([r["vx"], r["vy"], r["vz"]]) - B - km[2] @ S)
    return np.array(out)


def _micro(text: str) -> float:
    """A voltage as the page writes it ("21 µV", "1.2 mV"), in µV."""
    value, unit = text.split()
    return float(value) * {"µV": 1.0, "mV": 1e3, "V": 1e6}[unit]


def _texts(page, selector: str) -> list[str]:
    return page.eval_on_selector_all(selector, "cells => cells.map(c => c.textContent)")


def _runs(page) -> list[int]:
    """The runs the queue lists, in order."""
    return page.eval_on_selector_all("#queue tbody tr", "rows => rows.map(r => Number(r.dataset.run))")


def test_the_register_of_twenty_shows_three_due_within_30_days_and_one_overdue(lab, browser):
    page = _signed_in(browser, lab["url"])
    try:
        _check(page, lab["url"], "/instruments", "instruments.png")
        assert sorted(_rows(page, "#register")) == sorted(lab["serials"])
        words = page.eval_on_selector_all("#register tbody tr .state",
                                          "cells => cells.map(c => c.textContent.split(' ')[0])")
        states = dict(zip(_rows(page, "#register"), words, strict=True))
        assert {s for s, state in states.items() if state == "due"} == set(DUE_IN)
        assert {s for s, state in states.items() if state == "overdue"} == set(OVERDUE)
        assert {s for s, state in states.items() if state == "current"} == \
            set(lab["serials"]) - set(DUE_IN) - set(OVERDUE)

        _check(page, lab["url"], "/instruments?q=northwind")  # a customer, whatever its case
        assert sorted(_rows(page, "#register")) == lab["serials"][1::2]
        _check(page, lab["url"], "/instruments?q=TA-302")  # a model
        assert sorted(_rows(page, "#register")) == lab["serials"][2::3]

        _check(page, lab["url"], "/due", "due.png")
        today = date.today()
        assert _rows(page, "#overdue") == list(OVERDUE)
        assert page.text_content("#overdue tbody tr td:nth-child(6)") == \
            (today - timedelta(days=OVERDUE["ACC-0105"])).isoformat()
        assert _rows(page, "#soon") == sorted(DUE_IN, key=DUE_IN.get)  # soonest first
        shown = _texts(page, "#soon tbody tr td:nth-child(6)")
        assert shown == [(today + timedelta(days=d)).isoformat() for d in sorted(DUE_IN.values())]
        _check(page, lab["url"], "/due?within=90d")  # a wider window takes in two more (due in 70, 80 d)
        assert len(_rows(page, "#soon")) == len(DUE_IN) + 2
        response = page.goto(lab["url"] + "/due?within=soon")
        assert response is not None and response.status == 400
        assert "give a number of days, months or years" in page.text_content("main")
    finally:
        page.close()


def test_an_instruments_page_lists_its_calibrations_documents_and_drift(lab, browser):
    page = _signed_in(browser, lab["url"])
    try:
        _check(page, lab["url"], f"/instruments/{DRIFTED.lower()}", "instrument.png")  # any case
        assert page.text_content("h1").startswith(DRIFTED)
        assert page.locator("#calibrations tbody tr").count() == 2
        flagged = page.locator("#drift table:first-of-type td.flagged")
        assert flagged.count() == 1 and "drift" in flagged.text_content()  # B of sensor x, second row
        second_b = "#drift table:first-of-type tbody tr:nth-child(2) td:nth-child(2).flagged"
        assert page.locator(second_b).count() == 1
        assert page.locator("#drift table:not(:first-of-type) td.flagged").count() == 0
        # the plot of the same: loaded by the browser (a decoded image has a width), served as a PNG
        plot = page.locator("#drift img#coefficients-plot")
        assert plot.evaluate("img => img.complete && img.naturalWidth > 0")
        png = page.request.get(lab["url"] + plot.get_attribute("src"))
        assert png.status == 200 and png.headers["content-type"] == "image/png"

        _check(page, lab["url"], "/instruments/ACC-0042")  # the bench run: its run, its documents
        assert page.locator("#calibrations a[href='/runs/1']").count() == 1
        issued = json.loads((lab["bench"] / "certificate.json").read_text())
        for name, media in (("certificate.json", "application/json"),
                            ("certificate.dcc.xml", "application/xml"), ("report.pdf", "application/pdf")):
            link = page.locator(f"#calibrations a[href$='/{name}']")
            got = page.request.get(lab["url"] + link.get_attribute("href"))
            assert got.status == 200 and got.headers["content-type"].startswith(media), name
            if name == "certificate.json":  # as the lab database keeps it: the same certificate, sealed
                assert json.loads(got.body())["digest"] == issued["digest"]
            else:  # the files the run wrote
                assert got.body() == (lab["bench"] / name).read_bytes(), name
        assert issued["conformity"]["passed"] is False
        response = page.goto(lab["url"] + "/instruments/NO-SUCH")
        assert response is not None and response.status == 404
    finally:
        page.close()


def test_the_device_model_run_page_shows_residuals_within_twice_the_certificates(lab, browser):
    page = _signed_in(browser, lab["url"])
    try:
        _check(page, lab["url"], "/runs/2", "run-results.png")
        issued = json.loads((lab["device"] / "certificate.json").read_text())
        assert issued["fit"]["model"] == "device"
        assert page.text_content("#model") == "device model"
        # the residuals as the plot states them: RMS per sensor, against the certificate's own S_E
        ratios = [float(v) for v in _texts(page, "#residual-rms td.ratio")]
        assert len(ratios) == 3 and all(0.5 < r <= 2.0 for r in ratios), ratios
        # the RMS of K residuals with L = 15 parameters fitted (12 + 6 misalignments − the 3 the
        # plan leaves unidentified is not assumed: any L) is S_E·√((K − L)/K) < S_E
        assert all(r < 1.0 for r in ratios)
        # and they are the certificate's model applied to the readings the run folder holds
        mine = np.sqrt(np.mean(_device_model_residuals(lab["device"], issued) ** 2, axis=0)) * 1e6
        shown_rms = [_micro(t) for t in _texts(page, "#residual-rms tbody tr:first-child td")]
        assert shown_rms == pytest.approx(mine, rel=0.01), (shown_rms, mine)  # the page rounds to 3 digits
        assert page.is_visible("img.plot")
        png = page.request.get(lab["url"] + "/runs/2/residuals.png")
        assert png.status == 200 and png.headers["content-type"] == "image/png"
        u = issued["expanded_uncertainty"]["U"]
        shown = _texts(page, "#coefficients tbody tr td")
        assert len(shown) == 12 and all(" ± " in s for s in shown)
        stated = [float(s.split(" ± ")[1]) for s in shown]  # row by row: B, then S's rows; x, y, z
        assert stated == pytest.approx([u[i][j] for i in range(4) for j in range(3)], rel=0.05)  # 2 digits
        assert page.locator("#documents a").count() == 3
    finally:
        page.close()


def test_the_queue_shows_what_needs_attention_and_signing_takes_the_run_off_it(lab, browser):
    page = _signed_in(browser, lab["url"])
    try:
        _check(page, lab["url"], "/queue", "queue.png")
        assert _runs(page) == [1]  # the dry run is not listed by default
        attention = page.text_content("#queue tr[data-run='1'] td.attention")
        assert "out of tolerance" in attention
        _check(page, lab["url"], "/queue?dry=1")
        assert _runs(page) == [1, 2]

        _check(page, lab["url"], "/runs/1")
        assert page.text_content("#approved-by") == "Not approved yet."
        assert "out of tolerance" in page.text_content("#attention")
        assert page.text_content("#verdict").startswith("FAIL")
        page.fill("form[action='/runs/1/approve'] input[name=password]", PASSWORD)
        page.click("form[action='/runs/1/approve'] button[type=submit]")
        page.wait_for_selector("#message")
        approval = json.loads((lab["bench"] / "certificate.json").read_text())["approval"]
        _check(page, lab["url"], "/runs/1", "run-approved.png")
        by = page.text_content("#approved-by")
        assert "ada" in by and approval["approved_utc"][:19].replace("T", " ") in by
        _check(page, lab["url"], "/queue")
        assert page.locator("#queue").count() == 0 and page.is_visible("#empty")
    finally:
        page.close()


def test_a_viewer_reads_every_new_page_and_nobody_signed_out_does(lab, browser):
    import httpx

    for path in ("/queue", "/instruments", "/instruments/ACC-0042", "/due", "/runs/2",
                 f"/instruments/{DRIFTED}/coefficients.png"):
        answer = httpx.get(lab["url"] + path, follow_redirects=False, timeout=30)
        assert answer.status_code == 303 and answer.headers["location"].startswith("/login"), path
    page = _signed_in(browser, lab["url"], "vic", "vic's passphrase")
    try:
        for path in ("/queue", "/instruments", "/due"):
            response = page.goto(lab["url"] + path)
            assert response is not None and response.status == 200, path
        nav = page.eval_on_selector_all("header nav a", "links => links.map(a => a.getAttribute('href'))")
        assert {"/queue", "/instruments", "/due"} <= set(nav)
        png = page.request.get(lab["url"] + f"/instruments/{DRIFTED}/coefficients.png")
        assert png.status == 200 and png.headers["content-type"] == "image/png"
    finally:
        page.close()
