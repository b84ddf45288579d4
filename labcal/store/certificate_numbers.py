"""The lab's own certificate numbers in the lab database (`labcal.store.schema.certificate_numbers`):
the only SQL of them. A run gets one number, once: asked again (a reissue, a revision, a resume that
writes the certificate again) it gets the same. The next number in a scope is the largest there + 1,
inserted under the scope's unique sequence, so two benches numbering at once cannot take the same
one; the one that loses the race counts again. Nothing is ever deleted, so the sequence has no gap.
Works on SQLite and PostgreSQL alike (SQLAlchemy Core)."""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError

from labcal.errors import LabcalError
from labcal.store.schema import certificate_numbers

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine

TRIES = 40  # benches numbering at the same moment: each loser counts again, after a random pause
BACKOFF_S = 0.01  # the pause's scale: up to this many seconds times the tries lost so far


def assigned(engine: Engine, run_uuid: str, scope: int, make: Callable[[int], str]) -> str:
    """The number of the run ``run_uuid``: the one it has, else ``make(seq)`` with the next ``seq`` of
    ``scope``, recorded."""
    for lost in range(TRIES):
        if lost:  # two losers retrying in step would collide again: spread them apart
            time.sleep(random.uniform(0.0, BACKOFF_S * lost))
        try:
            with engine.begin() as conn:
                held = conn.execute(select(certificate_numbers.c.number)
                                    .where(certificate_numbers.c.run_uuid == run_uuid)).scalar_one_or_none()
                if held is not None:
                    return str(held)
                last = conn.execute(select(func.max(certificate_numbers.c.seq))
                                    .where(certificate_numbers.c.scope == scope)).scalar_one()
                seq = int(last or 0) + 1
                number = make(seq)
                conn.execute(certificate_numbers.insert().values(
                    scope=scope, seq=seq, number=number, run_uuid=run_uuid,
                    assigned_utc=datetime.now(UTC).isoformat(timespec="seconds")))
                return number
        except IntegrityError:  # another bench took this seq (or made this number) meanwhile
            continue
    raise LabcalError(f"no certificate number after {TRIES} tries: other benches keep taking the next one, "
                      "or the format makes a number already used (give it {seq})")
