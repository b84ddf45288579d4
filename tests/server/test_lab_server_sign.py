"""Signing on the run's page (21 CFR Part 11's electronic signature): a signed-in approver gives their
password again and the certificate names them, with the meaning "approved" and the time; a wrong
password signs nothing. Through the form, in Chromium, as the approver does it.

The run is a calibration through the real drivers against `labcal sim serve` (a dry run is never
approved), its draft issued as `labcal report` issues it; the server signs with the lab's key,
registered under the approver's name."""

from __future__ import annotations

import json

import pytest
from lab_server import accessible, add_user, served
from simulated_runs import bench_run

from labcal.app.run_documents import write_run_outputs
from labcal.cli import main


@pytest.mark.slow  # a bench run through the drivers, its report and an approval: some 35 s on two cores
def test_the_approver_signs_on_the_page_with_their_password(browser, tmp_path):
    db = tmp_path / "lab.sqlite"
    run_dir = bench_run(tmp_path / "run", db, "ACC-0042")
    write_run_outputs(run_dir, db=db)
    assert main(["certificate", "keygen", "--out", str(tmp_path / "lab")]) == 0
    assert main(["certificate", "approvers", "add", "ada", "--role", "Quality manager", "--public-key",
                 str(tmp_path / "lab.pub"), "--db", str(db)]) == 0
    add_user(str(db), "ada", "approver", "ada's passphrase")
    cert_path = run_dir / "certificate.json"
    with served(str(db), "--key", str(tmp_path / "lab.key")) as url:
        page = browser.new_page()
        try:
            page.goto(url + "/login?next=/runs/1")
            page.fill("input[name=name]", "ada")
            page.fill("input[name=password]", "ada's passphrase")
            page.click("button[type=submit]")
            page.wait_for_url(url + "/runs/1")
            assert page.is_visible("img.plot")  # the finished run's residuals
            accessible(page, "the run's page with its approval form")
            sign = "form[action='/runs/1/approve']"
            page.fill(f"{sign} input[name=password]", "not her passphrase")
            page.click(f"{sign} button[type=submit]")
            assert "nothing was signed" in (page.text_content("#message") or "")
            accessible(page, "a refused signature's answer")
            assert "approval" not in json.loads(cert_path.read_text())
            page.fill(f"{sign} input[name=password]", "ada's passphrase")
            page.click(f"{sign} button[type=submit]")
            page.wait_for_selector("#message", timeout=120_000)
            shown = page.text_content("#message") or ""
        finally:
            page.close()
    approval = json.loads(cert_path.read_text())["approval"]
    assert (approval["by"], approval["role"]) == ("ada", "Quality manager")
    assert f"approved by ada (Quality manager) at {approval['approved_utc']}" in shown
    assert main(["certificate", "verify", str(cert_path), "--db", str(db)]) == 0
