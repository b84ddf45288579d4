"""The database handles the application layer holds and hands back to the store.

A use case keeps an open lab database (`labcal.app.labdatabase.LabDatabase`) or a connection a
request opened, and passes it to the store's queries; it names their types from here, so that
nothing outside the store imports SQLAlchemy or sqlite3 to write a type hint (a journal's
connection is a `SQLiteConnection`).
"""

from sqlite3 import Connection as SQLiteConnection

from sqlalchemy.engine import Connection, Engine

__all__ = ["Connection", "Engine", "SQLiteConnection"]
