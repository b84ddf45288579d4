"""Approving through the lab server: only an approver (401 without a token, 403 for a viewer), signed
with the lab's key registered under the approver's name, the certificate then naming the authenticated
approver and verifying with `labcal certificate verify` against the registered keys; a run whose
folder the server cannot reach is answered 409 with where to approve instead.

The run is a calibration through the real drivers against `labcal sim serve` in another process (a
dry run is never approved), its draft certificate issued as `labcal report` issues it."""

from __future__ import annotations

import io
import json
import shutil
import sqlite3
from contextlib import redirect_stdout

import httpx
import pytest
from lab_server import add_user, served
from simulated_runs import bench_run

from labcal.app.run_documents import write_run_outputs
from labcal.cli import main


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    base = tmp_path_factory.mktemp("approve")
    db = base / "lab.sqlite"
    run_dir = bench_run(base / "run", db, "ACC-0042")
    write_run_outputs(run_dir, db=db)  # the draft certificate, as `labcal report` writes it
    assert main(["run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16", "--db", str(db),
                 "--out", str(base / "elsewhere")]) == 0
    shutil.rmtree(base / "elsewhere")  # run 2's folder is on another station's disk
    assert main(["certificate", "keygen", "--out", str(base / "lab")]) == 0
    assert main(["certificate", "approvers", "add", "ada", "--role", "Technical manager", "--public-key",
                 str(base / "lab.pub"), "--db", str(db)]) == 0
    tokens = {"ada": add_user(str(db), "ada", "approver", "ada's passphrase"),
              "vic": add_user(str(db), "vic", "viewer", "vic's passphrase")}
    with served(str(db), "--key", str(base / "lab.key")) as url:
        yield {"url": url, "db": db, "run_dir": run_dir, "tokens": tokens}


def _approve(lab, run_id: int, token: str | None) -> httpx.Response:
    headers = {} if token is None else {"Authorization": f"Bearer {token}"}
    return httpx.post(f"{lab['url']}/api/runs/{run_id}/approve", headers=headers, timeout=120)


def test_only_an_approver_approves_and_the_certificate_names_them(lab):
    shown = httpx.get(f"{lab['url']}/api/runs/1", headers={"Authorization": f"Bearer {lab['tokens']['vic']}"},
                      timeout=10).json()
    assert shown["simulated"] is False  # through the drivers, as on a bench: it may be approved
    assert _approve(lab, 1, None).status_code == 401
    assert _approve(lab, 1, "forged").status_code == 401
    assert _approve(lab, 1, lab["tokens"]["vic"]).status_code == 403
    cert_path = lab["run_dir"] / "certificate.json"
    assert json.loads(cert_path.read_text()).get("approval") is None  # the refusals signed nothing
    done = _approve(lab, 1, lab["tokens"]["ada"])
    assert done.status_code == 200, done.text
    approval = json.loads(cert_path.read_text())["approval"]
    assert (approval["by"], approval["role"]) == ("ada", "Technical manager")
    assert done.json()["by"] == "ada" and done.json()["approved_utc"] == approval["approved_utc"]
    printed = io.StringIO()
    with redirect_stdout(printed):  # against the keys registered in the lab database
        assert main(["certificate", "verify", str(cert_path), "--db", str(lab["db"]), "--json"]) == 0
    verified = json.loads(printed.getvalue())
    assert verified["valid"] is True and verified["approved_by"] == "ada"
    again = _approve(lab, 1, lab["tokens"]["ada"])
    assert again.status_code == 409 and "already approved" in again.json()["detail"]
    with sqlite3.connect(lab["db"]) as conn:  # the audit trail: the approval, and vic's 403 before it
        kinds = conn.execute("SELECT kind, account, client, detail FROM audit WHERE kind IN ('approved', "
                             "'refused') ORDER BY id").fetchall()
    assert [(k, a) for k, a, _, _ in kinds] == [("refused", None), ("refused", "vic"), ("approved", "ada")]
    assert kinds[-1][2] == "127.0.0.1" and done.json()["number"] in kinds[-1][3]


def test_a_run_whose_folder_is_out_of_reach_is_approved_where_it_is(lab):
    refused = _approve(lab, 2, lab["tokens"]["ada"])
    assert refused.status_code == 409
    detail = refused.json()["detail"]
    assert "not reachable from this server" in detail and "labcal certificate approve" in detail
    assert len(detail.splitlines()) == 1
    assert _approve(lab, 99, lab["tokens"]["ada"]).status_code == 404
