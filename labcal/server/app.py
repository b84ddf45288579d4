"""The lab server's ASGI application: JSON API, server-sent event streams, pages (issue 24).

Two ways in, never mixed:

- ``/api/…`` for programs: ``Authorization: Bearer TOKEN`` on every request (401 without or with a
  wrong one). No cookie is looked at there, so no other site can make a browser call the API with
  the user's session (the API has no CSRF surface).
- the pages for people: a session cookie from the login form (`labcal.server.sessions`), a CSRF token
  in every form, checked on every POST. The live parts of a run's page read a session-authenticated
  stream (``/runs/{id}/stream``; EventSource cannot send an Authorization header).

Roles on every route: every active user reads; only an approver approves (403 otherwise). A user
disabled while signed in is out at their next request.

Streams poll the lab database every `ServerSettings.poll_s` (the journal is written by other
processes, possibly on other machines: the database is the only thing they share) and send one event
per new point (``point``) and per journaled event (named by its kind: ``prompt``, ``fault``,
``status``, …), one ``run`` event when the run's status changes, and after each batch one
``progress`` event with the run's progress. Every event carries an id — the last point's seq and the
last event's id seen — so a client that reconnects with ``Last-Event-ID`` resumes where it left off.

Everything it reads or writes is a use case of the application layer (`labcal.app.lab`,
`labcal.app.users`, `labcal.app.server_approval`); this module is HTTP only: routes, who is asking,
sessions and CSRF, templates and the framing of the event streams.
"""

# No `from __future__ import annotations`: FastAPI reads the routes' annotations (Depends on local
# functions) when they are defined.

import asyncio
import json
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import Depends, FastAPI, Form, Header, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates

from labcal.app import lab, users
from labcal.app.certificates import Authentication
from labcal.app.labdatabase import LabDatabase
from labcal.app.server_approval import (
    ApproveAsUser,
    NotHere,
    approval_refused,
    approve_as_user,
    approved_file,
)
from labcal.errors import LabcalError
from labcal.server.sessions import COOKIE, Session, Sessions, csrf_ok

HERE = Path(__file__).parent
KEEP_ALIVE_S = 15.0
USER_CHECK_S = 5.0  # how soon an open stream of a user disabled meanwhile ends
STATUS_CLASS = {"running": "running", "complete": "complete", "interrupted": "stopped", "stopped": "stopped",
                "failed": "failed"}


@dataclass
class ServerSettings:
    lab: LabDatabase
    key: Path | None = None  # the lab's signing key
    poll_s: float = 0.5
    sessions: Sessions = field(default_factory=Sessions)


class SignIn(Exception):
    """A page needs a signed-in user: redirect to the login form."""


def create_app(settings: ServerSettings) -> FastAPI:
    app = FastAPI(title="labcal lab server", docs_url=None, redoc_url=None, openapi_url=None)
    templates = Jinja2Templates(directory=str(HERE / "templates"))
    templates.env.filters["duration"] = duration
    templates.env.filters["mount"] = mount_text
    templates.env.globals["status_class"] = lambda s: STATUS_CLASS.get(s, "other")
    app.mount("/static", StaticFiles(directory=str(HERE / "static")), name="static")
    db, sessions = settings.lab, settings.sessions
    app.state.sessions = sessions

    # --- who is asking ---------------------------------------------------------------------------
    def api_user(authorization: Annotated[str | None, Header()] = None) -> users.User:
        scheme, _, token = (authorization or "").partition(" ")
        user = users.by_token(db, token.strip()) if scheme.lower() == "bearer" else None
        if user is None:
            raise HTTPException(401, "give a valid API token: Authorization: Bearer TOKEN (`labcal user add` "
                                     "prints one)", headers={"WWW-Authenticate": "Bearer"})
        return user

    def api_approver(user: Annotated[users.User, Depends(api_user)]) -> users.User:
        if not user.may_approve:
            raise HTTPException(403, f"{user.name} is a {user.role}; only an approver approves certificates")
        return user

    def session_of(request: Request) -> Session | None:
        return sessions.get(request.cookies.get(COOKIE))

    def page_user(request: Request) -> users.User:
        session = session_of(request)
        user = users.named(db, session.user) if session is not None and session.user else None
        if user is None or not user.active:
            if session is not None and session.user:
                sessions.end(session)
            raise SignIn(request.url.path)
        request.state.session = session
        return user

    @app.exception_handler(SignIn)
    async def _sign_in(request: Request, exc: SignIn) -> Response:
        if request.url.path.endswith("/stream") or request.method != "GET":
            return JSONResponse({"detail": "sign in first"}, status_code=401)
        return RedirectResponse(f"/login?next={quote(str(exc.args[0]))}", status_code=303)

    def page(request: Request, template: str, user: users.User | None, status: int = 200, **context: Any
             ) -> Response:
        session = getattr(request.state, "session", None)
        values = {"user": user, "csrf": session.csrf if session else "", "lab_db": db.shown, **context}
        return templates.TemplateResponse(request, template, values, status_code=status)

    # --- the API ---------------------------------------------------------------------------------
    @app.get("/api/runs")
    def api_runs(user: Annotated[users.User, Depends(api_user)]) -> dict:
        return {"runs": lab.lab_runs(db)}

    @app.get("/api/runs/{run_id}")
    def api_run(run_id: int, user: Annotated[users.User, Depends(api_user)]) -> dict:
        found = lab.run_detail(db, run_id)
        if found is None:
            raise HTTPException(404, f"no run {run_id} in the lab database")
        return found

    @app.get("/api/runs/{run_id}/stream")
    def api_stream(run_id: int, request: Request, user: Annotated[users.User, Depends(api_user)],
                   last_event_id: Annotated[str | None, Header()] = None) -> Response:
        return stream_response(request, run_id, last_event_id, user)

    @app.post("/api/runs/{run_id}/approve")
    def api_approve(run_id: int, user: Annotated[users.User, Depends(api_approver)]) -> dict:
        done = approve_as(run_id, user, "API token")
        return done.to_json()

    @app.get("/api/runs/{run_id}/approved/{name}")
    def api_approved(run_id: int, name: str, user: Annotated[users.User, Depends(api_user)]) -> Response:
        return approved(run_id, name)

    def approved(run_id: int, name: str) -> Response:
        found = approved_file(db, run_id, name)
        if found is None:
            raise HTTPException(404, f"no {name} of run {run_id} approved by the lab server")
        return Response(found[1], media_type=found[0],
                        headers={"Content-Disposition": f'attachment; filename="{name}"'})

    @app.get("/api/runs/{run_id}/residuals.png")
    def api_residuals(run_id: int, user: Annotated[users.User, Depends(api_user)]) -> Response:
        return residuals(run_id)

    def approve_as(run_id: int, user: users.User, authentication: Authentication) -> Any:
        try:
            done = approve_as_user(db, ApproveAsUser(run_id, user, settings.key, authentication))
        except NotHere as exc:
            raise HTTPException(409, str(exc)) from None
        except LabcalError as exc:
            raise HTTPException(409, str(exc)) from None
        if done is None:
            raise HTTPException(404, f"no run {run_id} in the lab database")
        return done

    def residuals(run_id: int) -> Response:
        png = lab.residual_plot(db, run_id)
        if png is None:
            raise HTTPException(404, f"run {run_id} has too few readings to fit")
        return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=60"})

    # --- streams ---------------------------------------------------------------------------------
    def stream_response(request: Request, run_id: int, last_event_id: str | None, user: users.User
                        ) -> Response:
        if lab.run_progress(db, run_id) is None:
            raise HTTPException(404, f"no run {run_id} in the lab database")
        return StreamingResponse(events_of(request, run_id, cursor_of(last_event_id), user.name),
                                 media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    async def events_of(request: Request, run_id: int, cursor: lab.Cursor, user: str
                        ) -> AsyncIterator[str]:
        yield "retry: 2000\n\n"
        status: str | None = None
        quiet_since = checked = time.monotonic()
        first = True
        while not await request.is_disconnected():
            if time.monotonic() - checked > USER_CHECK_S:  # a user disabled meanwhile hears no more
                found = await run_in_threadpool(users.named, db, user)
                if found is None or not found.active:
                    return
                checked = time.monotonic()
            batch = await run_in_threadpool(lab.next_batch, db, lab.NextBatch(run_id, cursor, status, first))
            messages = [sse(item.kind, item.data, item.cursor) for item in batch.items]
            cursor, status, first = batch.cursor, batch.status, False
            for message in messages:
                yield message
            if messages:
                quiet_since = time.monotonic()
            elif time.monotonic() - quiet_since > KEEP_ALIVE_S:
                yield ": still here\n\n"
                quiet_since = time.monotonic()
            await asyncio.sleep(settings.poll_s)

    # --- pages -----------------------------------------------------------------------------------
    @app.get("/login", response_class=HTMLResponse)
    def login_form(request: Request, next: str = "/") -> Response:
        session = session_of(request) or sessions.open()
        request.state.session = session
        response = page(request, "login.html", None, next=safe_next(next), failed=False)
        set_cookie(request, response, session)
        return response

    @app.post("/login")
    def login(request: Request, name: Annotated[str, Form()], password: Annotated[str, Form()],
              csrf: Annotated[str, Form()] = "", next: Annotated[str, Form()] = "/") -> Response:
        session = session_of(request)
        if not csrf_ok(session, csrf):
            return forbidden_csrf(request)
        user = users.by_password(db, name, password)
        if user is None:
            request.state.session = session
            return page(request, "login.html", None, status=401, next=safe_next(next), failed=True, name=name)
        fresh = sessions.sign_in(session, user.name)
        response = RedirectResponse(safe_next(next), status_code=303)
        set_cookie(request, response, fresh)
        return response

    @app.post("/logout")
    def logout(request: Request, csrf: Annotated[str, Form()] = "") -> Response:
        session = session_of(request)
        if not csrf_ok(session, csrf):
            return forbidden_csrf(request)
        assert session is not None
        sessions.end(session)
        response = RedirectResponse("/login", status_code=303)
        response.delete_cookie(COOKIE, path="/")
        return response

    @app.get("/", response_class=HTMLResponse)
    def index(request: Request, user: Annotated[users.User, Depends(page_user)]) -> Response:
        overview = lab.lab_overview(db)
        return page(request, "index.html", user, stations=overview.stations, runs=overview.runs,
                    as_of_utc=overview.as_of_utc)

    @app.get("/runs/{run_id}", response_class=HTMLResponse)
    def run_page(request: Request, run_id: int, user: Annotated[users.User, Depends(page_user)],
                 message: str | None = None) -> Response:
        view = lab.run_view(db, run_id)
        if view is None:
            return page(request, "error.html", user, status=404,
                        message=f"No run {run_id} in the lab database.")
        refused = approval_refused(db, run_id, settings.key, user.name) \
            if user.may_approve and view.run["status"] == "complete" and not view.run["simulated"] else None
        return page(request, "run.html", user, run=view.run, recent=view.recent, message=message,
                    after=event_id_of(view.cursor), refused=refused)

    @app.get("/runs/{run_id}/stream")
    def page_stream(run_id: int, request: Request, user: Annotated[users.User, Depends(page_user)],
                    last_event_id: Annotated[str | None, Header()] = None, after: str | None = None
                    ) -> Response:
        # ``after``: where the page's own rendering left off (EventSource sends Last-Event-ID only
        # when it reconnects, and then that wins)
        return stream_response(request, run_id, last_event_id or after, user)

    @app.get("/runs/{run_id}/residuals.png")
    def page_residuals(run_id: int, user: Annotated[users.User, Depends(page_user)]) -> Response:
        return residuals(run_id)

    @app.get("/runs/{run_id}/approved/{name}")
    def page_approved(run_id: int, name: str, user: Annotated[users.User, Depends(page_user)]) -> Response:
        return approved(run_id, name)

    @app.post("/runs/{run_id}/approve", response_class=HTMLResponse)
    def page_approve(request: Request, run_id: int, user: Annotated[users.User, Depends(page_user)],
                     password: Annotated[str, Form()] = "", csrf: Annotated[str, Form()] = "") -> Response:
        if not csrf_ok(request.state.session, csrf):
            return forbidden_csrf(request)
        if not user.may_approve:
            return page(request, "error.html", user, status=403,
                        message=f"{user.name} is a {user.role}; only an approver approves certificates.")
        # The electronic signature (21 CFR Part 11 §11.200): the signer gives their password again.
        if users.by_password(db, user.name, password) is None:
            return run_page_message(request, run_id, user, "The password is not yours: nothing was signed.",
                                    401)
        try:
            done = approve_as(run_id, user, "password re-entered")
        except HTTPException as exc:
            return run_page_message(request, run_id, user, f"Not approved: {exc.detail}", exc.status_code)
        return run_page_message(request, run_id, user,
                                f"Certificate {done.number} approved by {done.by} ({done.role}) at "
                                f"{done.approved_utc}: signed with {done.signed_by}.", 200)

    def run_page_message(request: Request, run_id: int, user: users.User, message: str, status: int
                         ) -> Response:
        response = run_page(request, run_id, user, message)
        response.status_code = status
        return response

    def forbidden_csrf(request: Request) -> Response:
        return HTMLResponse("<!doctype html><title>Refused</title><p>This form has expired or did not come "
                            "from this server (CSRF check failed); <a href='/login'>start again</a>.</p>",
                            status_code=403)

    return app


def set_cookie(request: Request, response: Response, session: Session) -> None:
    response.set_cookie(COOKIE, session_owner(request).cookie(session), httponly=True,
                        samesite="strict", secure=request.url.scheme == "https", path="/")


def session_owner(request: Request) -> Sessions:
    return request.app.state.sessions


def safe_next(target: str) -> str:
    """Only a path of this server (no open redirect to another site)."""
    return target if target.startswith("/") and not target.startswith("//") and "\\" not in target else "/"


def cursor_of(last_event_id: str | None) -> lab.Cursor:
    """(last point seq, last event id) from a Last-Event-ID; a new client starts at the beginning."""
    try:
        seq, event_id = (last_event_id or "").split(":")
        return lab.Cursor(int(seq), int(event_id))
    except ValueError:
        return lab.Cursor()


def event_id_of(cursor: lab.Cursor) -> str:
    """The SSE event id that names ``cursor`` (what `cursor_of` reads back)."""
    return f"{cursor.seq}:{cursor.event_id}"


def sse(kind: str, data: Any, cursor: lab.Cursor) -> str:
    return f"id: {event_id_of(cursor)}\nevent: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def duration(seconds: float | None) -> str:
    """Rig seconds as people read them: 45 s, 12 min, 2 h 05 min."""
    if seconds is None:
        return "—"
    s = round(float(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def mount_text(mount: dict | None) -> str:
    if not mount:
        return "—"
    return f"y {mount['y_deg']:g}°, u {mount['u_deg']:g}°"
