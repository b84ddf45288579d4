"""The desk's and the register's pages are HTML-escaped and read-only, and need a signed-in user:
what a person typed into the register (a customer, a model, a note) or into a search box reaches the
page as text, never as markup; a serial holding a slash has its own page; every new page answers a
signed-out visitor with the sign-in form and any other method than GET with 405; a document of a
certificate the lab does not hold is 404."""

from __future__ import annotations

import re

import httpx
import pytest
from lab_server import add_user, served

from labcal.cli import main

PASSWORD = "vic's passphrase"
HOSTILE = '<script>alert("x")</script><img src=x onerror=alert(1)>'


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    db = str(tmp_path_factory.mktemp("desk-escaping") / "lab.sqlite")
    add_user(db, "vic", "viewer", PASSWORD)
    assert main(["instrument", "add", "ACC/0042", "--customer", HOSTILE, "--model", "TA-3<b>00</b>",
                 "--notes", HOSTILE, "--interval", "12m", "--db", db]) == 0
    with served(db) as url:
        client = httpx.Client(base_url=url, timeout=30)
        token = re.search(r'name="csrf" value="([^"]+)"', client.get("/login").text)
        assert token is not None
        signed = client.post("/login", data={"name": "vic", "password": PASSWORD, "csrf": token[1]})
        assert signed.status_code == 303
        yield {"url": url, "client": client}


def test_what_the_register_holds_and_a_search_reach_the_page_as_text(lab):
    client = lab["client"]
    for path in ("/instruments", "/instruments?q=ACC", "/instruments/ACC%2F0042", "/instruments/acc/0042",
                 "/due"):
        page = client.get(path)
        assert page.status_code == 200, path
        assert "<script>alert" not in page.text and "<img src=x" not in page.text, path
        assert "<b>00</b>" not in page.text, path
    shown = client.get("/instruments/acc/0042").text  # any case; the slash is part of the serial
    assert "&lt;script&gt;alert(&#34;x&#34;)&lt;/script&gt;" in shown and "TA-3&lt;b&gt;00&lt;/b&gt;" in shown
    searched = client.get("/instruments", params={"q": HOSTILE})
    assert searched.status_code == 200 and "<script>alert" not in searched.text
    assert searched.text.count('data-serial="') == 1  # the customer, as typed
    wild = client.get("/instruments", params={"q": "<script>%"})  # text, not a pattern: nothing matches
    assert "No instrument matches" in wild.text and "<script>%" not in wild.text
    assert client.get("/instruments", params={"q": "contoso"}).text.count('data-serial="') == 0
    assert client.get("/instruments", params={"q": "alert("}).text.count('data-serial="') == 1  # the customer


def test_every_new_page_needs_a_signed_in_user_and_only_reads(lab):
    stranger = httpx.Client(base_url=lab["url"], timeout=30, follow_redirects=False)
    for path in ("/queue", "/instruments", "/instruments/ACC%2F0042", "/due",
                 "/certificates/X/certificate.json"):
        answer = stranger.get(path)
        assert answer.status_code == 303 and answer.headers["location"].startswith("/login?next="), path
        assert lab["client"].post(path).status_code in (401, 405), path  # no route writes here
    client = lab["client"]
    assert client.get("/certificates/NO-SUCH/certificate.json").status_code == 404
    assert client.get("/certificates/NO-SUCH/passwd").status_code == 404
    assert client.get("/instruments/NO-SUCH").status_code == 404
    refused = client.get("/due", params={"within": "<i>soon</i>"})
    assert refused.status_code == 400 and "<i>soon</i>" not in refused.text
