"""The lab server (issue 24): one HTTP server for the whole lab, reading the lab database.

`labcal serve` runs it (`labcal.commands.serve` stays a thin front). What is here:

- `db` opens the lab database (SQLite file or PostgreSQL URL) as a SQLAlchemy engine and checks its
  schema is the one `labcal.run.schema` describes;
- `users` the lab's users (technician, approver, viewer): passwords under argon2, API tokens as
  SHA-256 of 256 random bits; shared with `labcal user`;
- `lab` the reads: runs, their progress, the next remount, their events (pure: nothing written);
- `sessions` the web login's signed session cookies and their CSRF tokens;
- `approve` a certificate approved through the server, with the lab's key, for the signed-in approver;
- `app` the ASGI application (FastAPI): the JSON API, the server-sent event streams and the pages.

FastAPI rather than bare Starlette: the API's authentication and roles are dependencies declared once
per route (a route cannot forget them without it showing in its signature), path parameters are
validated (a run id that is not an integer is a 422, not a crash), and it is Starlette underneath for
the streams, templates and static files. Nothing is loaded from a CDN: the lab may be offline.
"""
