"""The lab server: one HTTP server for the whole lab, reading the lab database.

`labcal serve` runs it (`labcal.commands.serve` stays a thin front). This package is HTTP only and
calls the application layer and nothing below it (an import contract says so): what it shows and
does are use cases of `labcal.app` — `labdatabase` (opening the lab database), `lab` (the reads:
stations, runs, progress, the next remount, events, the stream's next batch, the residual plot),
`users` (add, list, disable; a password or an API token to a user) and `server_approval` (a
certificate approved for the signed-in approver with the lab's key). What is here:

- `sessions` the web login's signed session cookies and their CSRF tokens (and the sign-in form's,
  which needs no session);
- `guards` what keeps it answering under attack, in memory: password failures per client address,
  event streams per user, the security headers of every answer;
- `app` the ASGI application (FastAPI): the routes of the JSON API, the server-sent event streams
  (their framing), the pages (templates) and the audit trail's page;
- `connections` uvicorn's h11 protocol with a deadline for request heads and a ceiling of
  connections under the open-file limit;
- `serving` the socket, TLS or a trusted proxy, and uvicorn.

FastAPI rather than bare Starlette: the API's authentication and roles are dependencies declared once
per route (a route cannot forget them without it showing in its signature), path parameters are
validated (a run id that is not an integer is a 422, not a crash), and it is Starlette underneath for
the streams, templates and static files. Nothing is loaded from a CDN: the lab may be offline.
"""
