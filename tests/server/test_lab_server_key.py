"""One lab server key for every approver: the key is registered with the role "lab server",
the server signs with it for the approver who is signed in, and the certificate names that approver,
their user id among the server's users, the meaning and how they authenticated; `labcal certificate
verify` accepts it and says who approved and through what. Refused: a technician, a key registered as
a person used for somebody else, a revoked server key, and the server's key used as a person.

Every run is a calibration through the real drivers against `labcal sim serve` (a dry run is never
approved), its draft issued as `labcal report` issues it. The expected user ids are read from the
users table with sqlite3, not from labcal."""

from __future__ import annotations

import io
import json
import re
import sqlite3
from contextlib import redirect_stdout

import httpx
import pytest
from lab_server import add_user, served
from simulated_runs import bench_run

from labcal.app.run_documents import write_run_outputs
from labcal.cli import main

# three bench runs through the drivers, each with its report, and three servers: about a minute on two cores
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("server_key")]  # built once, on one worker

PASSWORD = {"ada": "ada's passphrase", "bob": "bob's passphrase", "tom": "tom's passphrase 3"}


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    base = tmp_path_factory.mktemp("serverkey")
    db = base / "lab.sqlite"
    runs = {}
    for run_id, serial in ((1, "ACC-0101"), (2, "ACC-0102"), (3, "ACC-0103")):
        runs[run_id] = bench_run(base / f"run{run_id}", db, serial)
        write_run_outputs(runs[run_id], db=db)  # the draft certificate, as `labcal report` writes it
    for name in ("server", "old", "carol"):
        assert main(["certificate", "keygen", "--out", str(base / name)]) == 0
    for name, role, key in (("lab server", "lab server", "server"), ("old lab server", "lab server", "old"),
                            ("carol", "Technical manager", "carol")):
        assert main(["certificate", "approvers", "add", name, "--role", role, "--public-key",
                     str(base / f"{key}.pub"), "--db", str(db)]) == 0
    assert main(["certificate", "approvers", "revoke", "old lab server", "--db", str(db)]) == 0
    tokens = {"ada": add_user(str(db), "ada", "approver", PASSWORD["ada"]),
              "bob": add_user(str(db), "bob", "approver", PASSWORD["bob"]),
              "tom": add_user(str(db), "tom", "technician", PASSWORD["tom"])}
    with sqlite3.connect(db) as conn:
        ids = dict(conn.execute("SELECT name, id FROM users").fetchall())
    with served(str(db), "--key", str(base / "server.key")) as url:
        yield {"url": url, "db": db, "base": base, "runs": runs, "tokens": tokens, "ids": ids}


def _approve(url: str, run_id: int, token: str) -> httpx.Response:
    return httpx.post(f"{url}/api/runs/{run_id}/approve", headers={"Authorization": f"Bearer {token}"},
                      timeout=120)


def _verify(lab, run_id: int) -> dict:
    printed = io.StringIO()
    cert = lab["runs"][run_id] / "certificate.json"
    with redirect_stdout(printed):  # against the keys registered in the lab database
        assert main(["certificate", "verify", str(cert), "--db", str(lab["db"]), "--json"]) == 0
    return json.loads(printed.getvalue())


def _page_approve(lab, run_id: int, name: str) -> httpx.Response:
    """Sign in on the login page and approve on the run's page, giving the password again."""
    with httpx.Client(base_url=lab["url"], timeout=120) as client:
        csrf = re.search(r'name="csrf" value="([^"]+)"', client.get("/login").text)[1]
        client.post("/login", data={"name": name, "password": PASSWORD[name], "csrf": csrf})
        page = client.get(f"/runs/{run_id}")
        csrf = re.search(r'name="csrf" value="([^"]+)"', page.text)[1]
        return client.post(f"/runs/{run_id}/approve", data={"password": PASSWORD[name], "csrf": csrf})


def _approval(lab, run_id: int) -> dict | None:
    return json.loads((lab["runs"][run_id] / "certificate.json").read_text()).get("approval")


def test_two_approvers_approve_two_runs_through_one_server_key_and_verify_names_each(lab):
    refused = _approve(lab["url"], 1, lab["tokens"]["tom"])  # a technician's token
    assert refused.status_code == 403 and "only an approver" in refused.json()["detail"]
    assert _approval(lab, 1) is None  # the refusal signed nothing

    by_page = _page_approve(lab, 1, "ada")
    assert by_page.status_code == 200 and "approved by ada" in by_page.text, by_page.text
    by_api = _approve(lab["url"], 2, lab["tokens"]["bob"])
    assert by_api.status_code == 200, by_api.text
    assert by_api.json()["by"] == "bob" and "lab server" in by_api.json()["signed_by"]

    first, second = _approval(lab, 1), _approval(lab, 2)
    assert first["key_id"] == second["key_id"]  # one key, the server's
    assert (first["by"], first["role"]) == ("ada", "approver")
    assert first["server"] == {"signer": "lab server", "user_id": lab["ids"]["ada"], "meaning": "approved",
                               "authentication": "password re-entered"}
    assert (second["by"], second["role"]) == ("bob", "approver")
    assert second["server"] == {"signer": "lab server", "user_id": lab["ids"]["bob"], "meaning": "approved",
                                "authentication": "API token"}
    for run_id, name in ((1, "ada"), (2, "bob")):
        verified = _verify(lab, run_id)
        assert verified["valid"] is True and verified["approved_by"] == name
        assert verified["through_server"]["user_id"] == lab["ids"][name]
        assert f"approved by {name}" in verified["signed"] and "lab server" in verified["signed"]


def test_the_server_key_signs_for_no_one_else(lab, capsys):
    """The server's key used as a person's (`certificate approve --by "lab server"`) is refused."""
    run = lab["runs"][3]
    code = main(["certificate", "approve", str(run), "--by", "lab server", "--role", "lab server",
                 "--key", str(lab["base"] / "server.key"), "--db", str(lab["db"])])
    err = capsys.readouterr().err
    assert code == 2 and "signs only for an approver signed in" in err
    assert _approval(lab, 3) is None


@pytest.mark.parametrize("key,approver,refusal", [
    ("carol.key", "bob", "registered to 'carol'"),  # a key registered as a person signs for nobody else
    ("old.key", "ada", "was revoked"),  # a revoked server key signs for nobody
])
def test_a_server_key_that_may_not_sign_for_the_approver_is_refused(lab, key, approver, refusal):
    with served(str(lab["db"]), "--key", str(lab["base"] / key)) as url:
        refused = _approve(url, 3, lab["tokens"][approver])
    assert refused.status_code == 409
    assert refusal in refused.json()["detail"]
    assert _approval(lab, 3) is None
