"""The lab server's ASGI application: JSON API, server-sent event streams, pages.

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
`labcal.app.users`, `labcal.app.server_approval`; the approver's desk, a run's certificate and its
documents `labcal.app.desk`; the instrument register and what falls due
`labcal.app.instrument_pages`); this module is HTTP only: routes, who is asking,
sessions and CSRF, templates and the framing of the event streams.
"""

# No `from __future__ import annotations`: FastAPI reads the routes' annotations (Depends on local
# functions) when they are defined.

import asyncio
import json
import math
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from datetime import UTC, date, datetime, timedelta
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import Depends, FastAPI, Form, Header, HTTPException, Request
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.exception_handlers import request_validation_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.types import Receive, Scope, Send

from labcal.app import audit, desk, instrument_pages, lab, overview, users
from labcal.app.certificates import Authentication
from labcal.app.labdatabase import LabDatabase
from labcal.app.server_approval import (
    ApproveAsUser,
    approval_refused,
    approve_as_user,
    approved_file,
)
from labcal.app.station_state import Silence, State
from labcal.errors import LabcalError
from labcal.server.guards import ClientThrottle, SecurityHeaders, StreamQuota, TooManyStreams
from labcal.server.sessions import COOKIE, LOGIN_COOKIE, Session, Sessions, csrf_ok

HERE = Path(__file__).parent
KEEP_ALIVE_S = 15.0
USER_CHECK_S = 5.0  # how soon an open stream of a user disabled meanwhile ends
STATUS_CLASS = {"running": "running", "complete": "complete", "interrupted": "stopped", "stopped": "stopped",
                "failed": "failed"}
MAX_ID = 2**63 - 1  # the largest id the databases store (a larger one names nothing: 404)
RunId = Annotated[int, PathParam(ge=0, le=MAX_ID)]
AUDIT_ROWS = 200  # rows on the audit page
BODY_MAX = 16 * 1024  # the largest request body: the forms are a few fields (refused before it is read)


@dataclass
class ServerSettings:
    lab: LabDatabase
    key: Path | None = None  # the lab's signing key
    poll_s: float = 0.5
    sessions: Sessions = field(default_factory=Sessions)
    hosts: tuple[str, ...] = ()  # the Host header's accepted values (empty: any)
    throttle: ClientThrottle = field(default_factory=ClientThrottle)
    streams: StreamQuota = field(default_factory=StreamQuota)
    silence: Silence = field(default_factory=Silence)  # when a running bench is "not heard from"
    today: Callable[[], date] = date.today  # the day the register's and due pages count from


class SignIn(Exception):
    """A page needs a signed-in user: redirect to the login form."""


def create_app(settings: ServerSettings) -> FastAPI:
    app = FastAPI(title="labcal lab server", docs_url=None, redoc_url=None, openapi_url=None,
                  max_body_size=BODY_MAX)
    if settings.hosts:  # a request naming another host (DNS rebinding, a forged link) is refused
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=list(settings.hosts))
    app.add_middleware(SecurityHeaders)  # outermost: every answer, the refusals too
    templates = Jinja2Templates(directory=str(HERE / "templates"))
    templates.env.filters["duration"] = duration
    templates.env.filters["mount"] = mount_text
    templates.env.filters["clock"] = clock
    templates.env.globals["status_class"] = lambda s: STATUS_CLASS.get(s, "other")
    # a run's state (`labcal.app.overview.run_state`): the replay's states have their own colours
    templates.env.globals["state_class"] = \
        lambda s: f"state-{s}" if s in set(State) else STATUS_CLASS.get(s, "other")
    app.mount("/static", StaticFiles(directory=str(HERE / "static")), name="static")
    db, sessions = settings.lab, settings.sessions
    app.state.sessions = sessions

    # --- who is asking ---------------------------------------------------------------------------
    def api_user(request: Request, authorization: Annotated[str | None, Header()] = None) -> users.User:
        scheme, _, token = (authorization or "").partition(" ")
        user = users.by_token(db, token.strip()) if scheme.lower() == "bearer" else None
        if user is None:
            if authorization:  # a credential that is wrong (no credential at all is not worth a row)
                refused(request, None, 401, "a wrong or expired API token")
            raise HTTPException(401, "give a valid API token: Authorization: Bearer TOKEN (`labcal user add` "
                                     "prints one)", headers={"WWW-Authenticate": "Bearer"})
        return user

    def api_approver(request: Request, user: Annotated[users.User, Depends(api_user)]) -> users.User:
        if not user.may_approve:
            refused(request, user, 403, "approving, as a " + user.role)
            raise HTTPException(403, f"{user.name} is a {user.role}; only an approver approves certificates")
        return user

    def refused(request: Request, user: users.User | None, status: int, what: str) -> None:
        client = client_of(request)
        name = user.name if user else None
        if settings.throttle.note_refusal(f"{client} {name or ''}"):  # a row a minute per client and user
            audit.record(db, audit.Entry(audit.REFUSED, name, name, client,
                                         f"{status} {request.method} {request.url.path}: {what}"))

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> Response:
        """A path naming no integer in the databases' range names nothing: 404, like an absent run."""
        if any(error.get("loc", ("",))[0] == "path" for error in exc.errors()):
            return JSONResponse({"detail": "no such run in the lab database"}, status_code=404)
        return await request_validation_exception_handler(request, exc)

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
        # where the database is: for the lab's staff, not for viewers nor anonymous visitors
        shown = db.shown if user is not None and user.role != users.VIEWER else None
        values = {"user": user, "csrf": session.csrf if session else "", "lab_db": shown, **context}
        return templates.TemplateResponse(request, template, values, status_code=status)

    # --- the API ---------------------------------------------------------------------------------
    @app.get("/api/runs")
    def api_runs(user: Annotated[users.User, Depends(api_user)]) -> dict:
        return {"runs": [for_role(run, user) for run in lab.lab_runs(db)]}

    @app.get("/api/stations")
    def api_stations(user: Annotated[users.User, Depends(api_user)]) -> dict:
        """Every bench the lab knows with its state, as the overview shows it."""
        found = overview.lab_overview(db, settings.silence)
        stations = [{**s, "run": for_role(s["run"], user) if s["run"] else None} for s in found.stations]
        return {"as_of_utc": found.as_of_utc, "stations": stations}

    @app.get("/api/runs/{run_id}")
    def api_run(run_id: RunId, user: Annotated[users.User, Depends(api_user)]) -> dict:
        found = lab.run_detail(db, run_id)
        if found is None:
            raise HTTPException(404, f"no run {run_id} in the lab database")
        return for_role(found, user)

    @app.get("/api/runs/{run_id}/stream")
    def api_stream(run_id: RunId, request: Request, user: Annotated[users.User, Depends(api_user)],
                   last_event_id: Annotated[str | None, Header()] = None) -> Response:
        return stream_response(request, run_id, last_event_id, user)

    @app.post("/api/runs/{run_id}/approve")
    def api_approve(request: Request, run_id: RunId, user: Annotated[users.User, Depends(api_approver)]
                    ) -> dict:
        done = approve_as(request, run_id, user, "API token")
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
    def api_residuals(run_id: RunId, user: Annotated[users.User, Depends(api_user)]) -> Response:
        return residuals(run_id)

    def approve_as(request: Request, run_id: int, user: users.User, authentication: Authentication) -> Any:
        try:
            done = approve_as_user(db, ApproveAsUser(run_id, user, settings.key, authentication))
        except LabcalError as exc:  # NotHere included: this server cannot make the approval
            raise HTTPException(409, str(exc.spelled("web"))) from None
        if done is None:
            raise HTTPException(404, f"no run {run_id} in the lab database")
        audit.record(db, audit.Entry(audit.APPROVED, user.name, user.name, client_of(request),
                                     f"run {run_id}: certificate {done.number} ({authentication}), signed "
                                     f"with {done.signed_by}"))
        return done

    def residuals(run_id: int) -> Response:
        png = desk.residual_plot(db, run_id)
        if png is None:
            raise HTTPException(404, f"run {run_id} has too few readings to fit")
        return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=60"})

    # --- streams ---------------------------------------------------------------------------------
    def stream_response(request: Request, run_id: int, last_event_id: str | None, user: users.User
                        ) -> Response:
        cursor = cursor_of(last_event_id)
        if cursor is None:
            raise HTTPException(404, f"{last_event_id!r}: no such position in run {run_id}'s stream")
        if lab.run_progress(db, run_id) is None:
            raise HTTPException(404, f"no run {run_id} in the lab database")
        try:
            settings.streams.take(user.name)
        except TooManyStreams:
            raise HTTPException(429, f"{user.name} has {settings.streams.per_user} live streams open "
                                     "already; close one (a page of a run) first",
                                headers={"Retry-After": "10"}) from None
        return HeldStream(lambda: settings.streams.give_back(user.name),
                          events_of(request, run_id, cursor, user.name), media_type="text/event-stream",
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
        return login_page(request, next, 200)

    def login_page(request: Request, next: str, status: int, alert: str | None = None, name: str = "",
                   retry_after_s: float | None = None) -> Response:
        """The sign-in form: no session (anonymous visitors cost no memory), a signed double-submit
        CSRF token in a cookie of its own and in the form."""
        token = sessions.login_token(request.cookies.get(LOGIN_COOKIE))
        response = templates.TemplateResponse(
            request, "login.html", {"user": None, "csrf": token, "next": safe_next(next), "alert": alert,
                                    "name": name}, status_code=status)
        response.set_cookie(LOGIN_COOKIE, token, httponly=True, samesite="strict", path="/login",
                            secure=request.url.scheme == "https")
        if retry_after_s is not None:
            response.headers["Retry-After"] = retry_after(retry_after_s)
        return response

    @app.post("/login")
    def login(request: Request, name: Annotated[str, Form()], password: Annotated[str, Form()],
              csrf: Annotated[str, Form()] = "", next: Annotated[str, Form()] = "/") -> Response:
        if not sessions.login_token_ok(request.cookies.get(LOGIN_COOKIE), csrf):
            return forbidden_csrf(request)
        checked = check_password(request, users.PasswordCheck(name, password, client_of(request)))
        if isinstance(checked, Refused):
            return login_page(request, next, checked.status, checked.message, name, checked.retry_after_s)
        fresh = sessions.sign_in(session_of(request), checked.name)
        response = RedirectResponse(safe_next(next), status_code=303)
        set_cookie(request, response, fresh)
        response.delete_cookie(LOGIN_COOKIE, path="/login")
        return response

    def check_password(request: Request, attempt: users.PasswordCheck) -> users.User | Refused:
        """A password checked, throttled per client address here and per account in the lab database
        (`users.check_password`); the refusal as the pages say it."""
        client = attempt.client or "?"
        wait = settings.throttle.wait_s(client)
        if wait > 0:
            return Refused(429, f"Too many wrong passwords from your address: try again in {wait:.0f} s.",
                           wait)
        try:
            checked = users.check_password(db, attempt)
        except users.Busy:
            return Refused(503, "The server is busy checking other passwords: try again in a moment.", 1.0)
        if checked.user is not None:
            return checked.user
        if checked.heard:
            settings.throttle.failed(client)
        if checked.locked:
            return Refused(429, "This account is locked after repeated wrong passwords; an administrator "
                                "lifts the lock (labcal user unlock NAME).")
        if checked.heard:
            return Refused(401, "Wrong name or password." if not attempt.signature
                           else "The password is not yours: nothing was signed.")
        return Refused(429, f"Too many wrong passwords for this account: try again in "
                            f"{checked.wait_s:.0f} s.", checked.wait_s)

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
        found = overview.lab_overview(db, settings.silence)
        return page(request, "index.html", user, stations=found.stations, runs=found.runs,
                    as_of_utc=found.as_of_utc)

    @app.get("/audit", response_class=HTMLResponse)
    def audit_page(request: Request, user: Annotated[users.User, Depends(page_user)]) -> Response:
        """The audit trail, for approvers (who answer for what the server signed)."""
        if not user.may_approve:
            refused(request, user, 403, "the audit trail, as a " + user.role)
            return page(request, "error.html", user, status=403,
                        message=f"{user.name} is a {user.role}; only an approver reads the audit trail.")
        return page(request, "audit.html", user, rows=audit.newest(db, AUDIT_ROWS), broken=audit.verify(db),
                    total=audit.count(db))

    @app.get("/runs/{run_id}", response_class=HTMLResponse)
    def run_page(request: Request, run_id: RunId, user: Annotated[users.User, Depends(page_user)]
                 ) -> Response:
        return run_page_of(request, run_id, user, None)

    def run_page_of(request: Request, run_id: int, user: users.User, message: str | None) -> Response:
        """A run's page; ``message``: the answer to the approval just made (never from the URL, where
        anyone could write a message above the form and send the link)."""
        view = lab.run_view(db, run_id)
        if view is None:
            return page(request, "error.html", user, status=404,
                        message=f"No run {run_id} in the lab database.")
        refused = approval_refused(db, run_id, settings.key, user.name) \
            if user.may_approve and view.run["status"] == "complete" and not view.run["simulated"] else None
        results = desk.run_results(db, run_id) if view.run["status"] == "complete" else None
        return page(request, "run.html", user, run=view.run, recent=view.recent, message=message,
                    after=event_id_of(view.cursor), refused=refused, results=results,
                    state=overview.run_state(db, view.run, settings.silence))

    @app.get("/queue", response_class=HTMLResponse)
    def queue_page(request: Request, user: Annotated[users.User, Depends(page_user)], dry: bool = False
                   ) -> Response:
        """The approver's desk: the certificates waiting for approval, what needs attention in each."""
        return page(request, "queue.html", user, queue=desk.queue(db, dry), dry=dry)

    @app.get("/instruments", response_class=HTMLResponse)
    def instruments_page(request: Request, user: Annotated[users.User, Depends(page_user)], q: str = ""
                         ) -> Response:
        search, today = q.strip()[:instrument_pages.SEARCH_MAX], settings.today()
        return page(request, "instruments.html", user, q=search, today=today,
                    rows=instrument_pages.register(db, search or None, today))

    @app.get("/instruments/{serial:path}/coefficients.png")
    def instrument_coefficients(serial: str, user: Annotated[users.User, Depends(page_user)]) -> Response:
        png = instrument_pages.coefficients_png(db, serial)
        if png is None:
            raise HTTPException(404, f"{serial}: no registered instrument with a calibration to plot")
        return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=60"})

    @app.get("/instruments/{serial:path}", response_class=HTMLResponse)
    def instrument_page(request: Request, serial: str, user: Annotated[users.User, Depends(page_user)]
                        ) -> Response:
        today = settings.today()
        try:
            shown = instrument_pages.instrument_page(db, serial, today)
        except LabcalError as exc:
            return page(request, "error.html", user, status=404, message=str(exc.spelled("web")))
        return page(request, "instrument.html", user, shown=shown, today=today)

    @app.get("/due", response_class=HTMLResponse)
    def due_page(request: Request, user: Annotated[users.User, Depends(page_user)], within: str = "30d"
                 ) -> Response:
        today = settings.today()
        try:
            found = instrument_pages.due(db, within, today)
        except LabcalError as exc:
            return page(request, "error.html", user, status=400, message=str(exc.spelled("web")))
        return page(request, "due.html", user, due=found, within=within.strip(), today=today)

    @app.get("/certificates/{certificate_id:path}/{name}")
    def certificate_file(certificate_id: str, name: str, user: Annotated[users.User, Depends(page_user)]
                         ) -> Response:
        found = desk.certificate_document(db, certificate_id, name)
        if found is None:
            raise HTTPException(404, f"no {name} of certificate {certificate_id} in the lab database")
        saved = download_name(certificate_id, name)
        return Response(found[1], media_type=found[0],
                        headers={"Content-Disposition": f'attachment; filename="{saved}"'})

    @app.get("/runs/{run_id}/stream")
    def page_stream(run_id: RunId, request: Request, user: Annotated[users.User, Depends(page_user)],
                    last_event_id: Annotated[str | None, Header()] = None, after: str | None = None
                    ) -> Response:
        # ``after``: where the page's own rendering left off (EventSource sends Last-Event-ID only
        # when it reconnects, and then that wins)
        return stream_response(request, run_id, last_event_id or after, user)

    @app.get("/runs/{run_id}/residuals.png")
    def page_residuals(run_id: RunId, user: Annotated[users.User, Depends(page_user)]) -> Response:
        return residuals(run_id)

    @app.get("/runs/{run_id}/approved/{name}")
    def page_approved(run_id: int, name: str, user: Annotated[users.User, Depends(page_user)]) -> Response:
        return approved(run_id, name)

    @app.post("/runs/{run_id}/approve", response_class=HTMLResponse)
    def page_approve(request: Request, run_id: RunId, user: Annotated[users.User, Depends(page_user)],
                     password: Annotated[str, Form()] = "", csrf: Annotated[str, Form()] = "") -> Response:
        if not csrf_ok(request.state.session, csrf):
            return forbidden_csrf(request)
        if not user.may_approve:
            refused(request, user, 403, "approving, as a " + user.role)
            return page(request, "error.html", user, status=403,
                        message=f"{user.name} is a {user.role}; only an approver approves certificates.")
        # The electronic signature (21 CFR Part 11 §11.200): the signer gives their password again.
        checked = check_password(request, users.PasswordCheck(user.name, password, client_of(request),
                                                               signature=True))
        if isinstance(checked, Refused):
            response = run_page_message(request, run_id, user, checked.message, checked.status)
            if checked.retry_after_s is not None:
                response.headers["Retry-After"] = retry_after(checked.retry_after_s)
            return response
        try:
            done = approve_as(request, run_id, user, "password re-entered")
        except HTTPException as exc:
            return run_page_message(request, run_id, user, f"Not approved: {exc.detail}", exc.status_code)
        return run_page_message(request, run_id, user,
                                f"Certificate {done.number} approved by {done.by} ({done.role}) at "
                                f"{done.approved_utc}: signed with {done.signed_by}.", 200)

    def run_page_message(request: Request, run_id: int, user: users.User, message: str, status: int
                         ) -> Response:
        response = run_page_of(request, run_id, user, message)
        response.status_code = status
        return response

    def forbidden_csrf(request: Request) -> Response:
        return HTMLResponse("<!doctype html><title>Refused</title><p>This form has expired or did not come "
                            "from this server (CSRF check failed); <a href='/login'>start again</a>.</p>",
                            status_code=403)

    return app


class HeldStream(StreamingResponse):
    """A stream that gives its place back (``release``) however it ends: finished, cancelled when
    the client goes, or before its first event (a generator that never started runs no cleanup)."""

    def __init__(self, release: Callable[[], None], *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.release = release

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.release()


def for_role(run: dict, user: users.User) -> dict:
    """A run as ``user`` may see it: a viewer is not told where its folder is on the station's disk."""
    return run if user.role != users.VIEWER else {k: v for k, v in run.items() if k != "run_dir"}


@dataclass(frozen=True)
class Refused:
    """A password not checked or not right, as the pages say it."""

    status: int  # 401 wrong, 429 throttled or locked, 503 too many being checked
    message: str
    retry_after_s: float | None = None


def retry_after(seconds: float) -> str:
    """A Retry-After in whole seconds, rounded up: a client that obeys it is heard."""
    return str(max(1, math.ceil(seconds)))


def client_of(request: Request) -> str:
    """The client's address (a trusted proxy's X-Forwarded-For, when there is one: uvicorn's)."""
    return request.client.host if request.client else "?"


def set_cookie(request: Request, response: Response, session: Session) -> None:
    response.set_cookie(COOKIE, session_owner(request).cookie(session), httponly=True,
                        samesite="strict", secure=request.url.scheme == "https", path="/")


def session_owner(request: Request) -> Sessions:
    return request.app.state.sessions


def safe_next(target: str) -> str:
    """Only a path of this server (no open redirect to another site)."""
    return target if target.startswith("/") and not target.startswith("//") and "\\" not in target else "/"


def cursor_of(last_event_id: str | None) -> lab.Cursor | None:
    """(last point seq, last event id) from a Last-Event-ID; a new client starts at the beginning.
    None: a position beyond any the databases can hold."""
    try:
        seq, event_id = (last_event_id or "").split(":")
        cursor = lab.Cursor(int(seq), int(event_id))
    except ValueError:
        return lab.Cursor()
    return cursor if -MAX_ID <= cursor.seq <= MAX_ID and -MAX_ID <= cursor.event_id <= MAX_ID else None


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


def download_name(certificate_id: str, name: str) -> str:
    """A downloaded document's file name: the certificate's number before the document's name, with
    nothing but letters, digits, dots, dashes and underscores (a header value is no place for quotes)."""
    safe = "".join(c if c.isascii() and (c.isalnum() or c in "._-") else "_" for c in certificate_id)
    return f"{safe}-{name}"


def clock(utc: str | None, seconds: bool = False) -> str:
    """A UTC time (ISO 8601) as the lab reads it: UTC, and beside it the server's local time (the
    lab's) where that is another zone: "14:05 UTC (15:05 CET)"; the date too when it is not today's."""
    if not utc:
        return "—"
    when = datetime.fromisoformat(utc)
    when = when.replace(tzinfo=UTC) if when.tzinfo is None else when.astimezone(UTC)
    local = when.astimezone()
    shape = "%H:%M:%S" if seconds else "%H:%M"
    day = "" if when.date() == datetime.now(UTC).date() else when.strftime("%Y-%m-%d ")
    text = f"{day}{when.strftime(shape)} UTC"
    if local.utcoffset() != timedelta(0):
        text += f" ({local.strftime(shape)} {local.strftime('%Z') or local.strftime('%z')})"
    return text


def mount_text(mount: dict | None) -> str:
    if not mount:
        return "—"
    angles = f"y {mount['y_deg']:g}°, u {mount['u_deg']:g}°"
    return f"{mount['number']} ({angles})" if mount.get("number") else angles
