"""The register's and due pages count from the day the server's settings give (``today``), not the
machine's clock: a server pinned to a day says so on its due page, whatever day the test runs."""

from __future__ import annotations

import re
from datetime import date

from fastapi.testclient import TestClient
from lab_server import add_user

from labcal.app.labdatabase import OpenLab, open_lab
from labcal.server.app import ServerSettings, create_app

PASSWORD = "a long passphrase 1"
PINNED = date(2031, 5, 17)  # a day no test run falls on


def test_the_due_page_counts_from_the_day_the_settings_pin(tmp_path):
    db = str(tmp_path / "lab.sqlite")
    lab = open_lab(OpenLab(db, must_exist=False))
    add_user(db, "ada", "viewer", PASSWORD)
    try:
        with TestClient(create_app(ServerSettings(lab, today=lambda: PINNED))) as client:
            token = re.search(r'name="csrf" value="([^"]+)"', client.get("/login").text)
            assert token is not None
            signed = client.post("/login", data={"name": "ada", "password": PASSWORD, "csrf": token[1]},
                                 follow_redirects=False)
            assert signed.status_code == 303
            shown = client.get("/due")
    finally:
        lab.close()
    assert shown.status_code == 200
    assert "from 2031-05-17." in shown.text and f"from {date.today().isoformat()}." not in shown.text
