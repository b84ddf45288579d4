"""The lab server's accounts as the lab database keeps them (the ``users`` table): added, read,
disabled and given new secrets here. Who may do what, and how a password or token is checked, is
`labcal.app.users`'s; only hashes are stored.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError

from labcal.errors import LabcalError
from labcal.store.schema import users

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine

# A user as the application sees one: (id, name, role, created_utc, disabled_utc)
COLUMNS = (users.c.id, users.c.name, users.c.role, users.c.created_utc, users.c.disabled_utc)


class NameTaken(LabcalError):
    """The name is a user's already (``meanwhile``: added by someone else since it was looked up)."""

    def __init__(self, name: str, meanwhile: bool):
        super().__init__(name)
        self.meanwhile = meanwhile


def insert(engine: Engine, row: dict[str, Any]) -> int:
    """Add the user ``row`` (the table's columns but ``id``); their id. `NameTaken` when the name is
    a user's, before or meanwhile."""
    try:
        with engine.begin() as conn:
            if conn.execute(select(users.c.id).where(users.c.name == row["name"])).first() is not None:
                raise NameTaken(row["name"], meanwhile=False)
            key = conn.execute(users.insert().values(**row)).inserted_primary_key
            assert key is not None  # an INSERT of one row into a table with a primary key
            return int(key[0])
    except IntegrityError:
        raise NameTaken(row["name"], meanwhile=True) from None


def every(engine: Engine) -> list[tuple]:
    """Every user (`COLUMNS`), in the order they were added."""
    with engine.connect() as conn:
        return [tuple(r) for r in conn.execute(select(*COLUMNS).order_by(users.c.id))]


def named(engine: Engine, name: str) -> tuple | None:
    """The user ``name`` (`COLUMNS`), if any."""
    with engine.connect() as conn:
        row = conn.execute(select(*COLUMNS).where(users.c.name == name)).first()
    return None if row is None else tuple(row)


def disable(engine: Engine, name: str, when: str) -> tuple[bool, str | None, list[str]]:
    """Disable the active user ``name`` at ``when``: whether it was done; if not, when they were
    disabled before (None: no such user) and every user's name, read in the same transaction."""
    with engine.begin() as conn:
        done = conn.execute(update(users).where(users.c.name == name, users.c.disabled_utc.is_(None))
                            .values(disabled_utc=when))
        if done.rowcount == 1:
            return True, None, []
        row = conn.execute(select(users.c.disabled_utc).where(users.c.name == name)).first()
        known = [r[0] for r in conn.execute(select(users.c.name).order_by(users.c.id))]
        return False, None if row is None else row[0], known


def with_token(engine: Engine, hashed: str) -> tuple[tuple, str | None] | None:
    """The user (`COLUMNS`) whose token has the hash ``hashed``, and when it was issued."""
    with engine.connect() as conn:
        row = conn.execute(select(*COLUMNS, users.c.token_utc).where(users.c.token_hash == hashed)).first()
    return None if row is None else (tuple(row[:-1]), row[-1])


def with_password(engine: Engine, name: str) -> tuple[tuple, str] | None:
    """The user ``name`` (`COLUMNS`) and their password's hash."""
    with engine.connect() as conn:
        row = conn.execute(select(*COLUMNS, users.c.password_hash).where(users.c.name == name)).first()
    return None if row is None else (tuple(row[:-1]), row[-1])


def change(engine: Engine, name: str, **values: str) -> None:
    """Set the columns ``values`` of the user ``name`` (a new password's or token's hash)."""
    with engine.begin() as conn:
        conn.execute(update(users).where(users.c.name == name).values(**values))
