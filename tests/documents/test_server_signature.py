"""Whom the lab server's key may have signed for (`labcal.documents.approvers.problems` with a
`ServerSignature`): only a user who was, at the approval's time, an active approver of the lab server,
under the id and name the approval states, and only with a key registered with the role "lab server".

The users' times are set here with sqlite3 to fixed instants, so that "before", "between" and "after"
are the test's own, not the clock's."""

from __future__ import annotations

import sqlite3

import pytest

from labcal.app.labdatabase import OpenLab, open_lab
from labcal.app.users import AddUser, add
from labcal.cli import main
from labcal.documents.approval import key_id, load_public_key
from labcal.documents.approvers import problems
from labcal.documents.certificate import ServerSignature

CREATED, DISABLED = "2026-01-01T00:00:00+00:00", "2026-06-01T00:00:00+00:00"


@pytest.fixture
def lab(tmp_path):
    db = tmp_path / "lab.sqlite"
    opened = open_lab(OpenLab(str(db), must_exist=False))
    try:
        ids = {name: add(opened, AddUser(name, role, "a long passphrase")).user.id
               for name, role in (("ada", "approver"), ("tom", "technician"))}
    finally:
        opened.close()
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE users SET created_utc = ?", (CREATED,))
        conn.execute("UPDATE users SET disabled_utc = ? WHERE name = 'ada'", (DISABLED,))
    kids = {}
    for name, role in (("lab server", "lab server"), ("carol", "Technical manager")):
        out = tmp_path / name.replace(" ", "-")
        assert main(["certificate", "keygen", "--out", str(out)]) == 0
        assert main(["certificate", "approvers", "add", name, "--role", role, "--public-key",
                     f"{out}.pub", "--db", str(db)]) == 0
        kids[name] = key_id(load_public_key(f"{out}.pub"))
    return {"db": db, "ids": ids, "kids": kids}


def _for(lab, user: str, user_id: int | None = None, signer: str = "lab server") -> ServerSignature:
    return ServerSignature(signer=signer, user_id=user_id or lab["ids"][user], meaning="approved",
                           authentication="API token")


def test_an_active_approver_at_the_time_is_accepted(lab):
    assert problems(lab["kids"]["lab server"], "ada", "approver", lab["db"], _for(lab, "ada"),
                    "2026-03-01T12:00:00+00:00") == []


@pytest.mark.parametrize(("when", "reason"), [("2025-12-31T23:59:59+00:00", "became a user"),
                                              ("2026-06-01T00:00:00+00:00", "was disabled"),
                                              ("2026-07-01T00:00:00+00:00", "was disabled")])
def test_before_the_user_was_added_or_once_disabled_is_refused(lab, when, reason):
    found = problems(lab["kids"]["lab server"], "ada", "approver", lab["db"], _for(lab, "ada"), when)
    assert len(found) == 1 and reason in found[0]


def test_a_technician_another_id_or_another_signer_is_refused(lab):
    when = "2026-03-01T12:00:00+00:00"
    kid = lab["kids"]["lab server"]
    assert "not an approver" in " ".join(problems(kid, "tom", "approver", lab["db"], _for(lab, "tom"), when))
    wrong_id = problems(kid, "ada", "approver", lab["db"], _for(lab, "ada", user_id=lab["ids"]["tom"]), when)
    assert "is 'tom', not 'ada'" in " ".join(wrong_id)
    assert "no user 99" in " ".join(problems(kid, "ada", "approver", lab["db"], _for(lab, "ada", 99), when))
    other = problems(kid, "ada", "approver", lab["db"], _for(lab, "ada", signer="lab server 2"), when)
    assert "not 'lab server 2'" in " ".join(other)


def test_a_persons_key_never_signs_for_someone_else_and_the_servers_never_as_a_person(lab):
    when = "2026-03-01T12:00:00+00:00"
    as_server = problems(lab["kids"]["carol"], "ada", "approver", lab["db"], _for(lab, "ada"), when)
    assert "registered to 'carol' as a person" in " ".join(as_server)
    as_person = problems(lab["kids"]["lab server"], "lab server", "lab server", lab["db"])
    assert "signs only for an approver signed in" in " ".join(as_person)
    assert problems(lab["kids"]["carol"], "carol", "Technical manager", lab["db"]) == []  # her own: as before


def test_the_command_lines_server_role_is_the_registrys():
    from labcal.app.certificates import SERVER_ROLE
    from labcal.documents.approvers import SERVER_ROLE as REGISTRY_ROLE

    assert SERVER_ROLE == REGISTRY_ROLE == "lab server"
