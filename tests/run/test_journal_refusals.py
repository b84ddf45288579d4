"""What the journal's database refuses reaches the run machinery as the store's own error type, one
line naming the file, so that a caller that may go on without the write (the sequencer keeping the
settling pool) catches a JournalError and never the driver's exception."""

from __future__ import annotations

import pytest

from labcal.errors import LabcalError
from labcal.store.journal import Journal, JournalError


def test_a_statement_the_journal_refuses_is_a_journal_error_naming_the_file(tmp_path):
    path = tmp_path / "journal.sqlite"
    with Journal(path) as journal, pytest.raises(JournalError) as raised:
        with journal.refusals():
            journal.db.execute("INSERT INTO no_such_table VALUES (1)")
    assert isinstance(raised.value, LabcalError)
    assert str(path) in str(raised.value) and "no_such_table" in str(raised.value)


def test_what_the_database_accepts_passes_through_and_other_errors_are_left_alone(tmp_path):
    with Journal(tmp_path / "journal.sqlite") as journal:
        with journal.refusals():
            assert journal.db.execute("SELECT 1").fetchone() == (1,)
        with pytest.raises(KeyError), journal.refusals():
            raise KeyError("not the database's")
