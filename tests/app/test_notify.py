"""Notifications through apprise, received for real: apprise's ``json://`` posts each one
to an HTTP endpoint this test serves on a free port. The texts expected are written here from the
plan and the station chosen (Soto Table 3's mounts in the technician's words), the run's own files
(run.json, fit.json) and the emulated alarm's meaning in the AZ manual — never from the notifier."""

from __future__ import annotations

import json
import socket
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from cli import cli
from emulators import free_port, no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.plans import load_plan
from labcal.run.notify import Message, Notifications

EMULATE = ["--emulate", "--time-scale", "1000", "--no-report"]
BENCH = "bench 4 (north)"  # the bench's name in the lab database ($LABCAL_STATION)
SERVER_URL = "https://lab.example.org/labcal"


class Inbox:
    """What the endpoint received: one dict per notification (apprise's JSON: title, message, …)."""

    def __init__(self) -> None:
        self.received: list[dict] = []
        self.arrived = threading.Condition()

    def bodies(self) -> list[str]:
        return [doc["message"] for doc in self.received]

    def wait_for(self, count: int, timeout: float = 10.0) -> list[str]:
        with self.arrived:
            self.arrived.wait_for(lambda: len(self.received) >= count, timeout)
        return self.bodies()


@contextmanager
def endpoint() -> Iterator[tuple[str, Inbox]]:
    """A local HTTP endpoint for apprise's ``json://`` on a free port; yields its URL and inbox."""
    inbox = Inbox()

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 - http.server's name
            doc = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
            with inbox.arrived:  # kept before apprise hears "sent": a drained queue is all in the inbox
                inbox.received.append(doc)
                inbox.arrived.notify_all()
            self.send_response(200)
            self.end_headers()

        def log_message(self, *args: object) -> None:  # the test's stderr is the run's
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"json://127.0.0.1:{server.server_address[1]}/", inbox
    finally:
        server.shutdown()
        server.server_close()


def described(y_deg: float, u_deg: float) -> str:
    """A mount as the technician is told it (Soto Table 3: u 180° = bottom of the plate, y 180° = x
    sensor backward), with its angles."""
    side = "bottom" if u_deg == 180 else "top"
    way = "backward" if y_deg == 180 else "forward"
    return f"{side} side of the plate, x sensor pointing {way} (y={y_deg:g}°, u={u_deg:g}°)"


def journaled_points(db: Path, run_id: int) -> int:
    with sqlite3.connect(db) as con:
        return con.execute("SELECT count(*) FROM points WHERE run_id = ?", (run_id,)).fetchone()[0]


def lab_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, server_url: str = SERVER_URL) -> None:
    """A lab file naming the lab server's public address, and this bench's name in $LABCAL_STATION."""
    lab = tmp_path / "lab.toml"
    lab.write_text(f'server_url = "{server_url}"\n', encoding="utf-8")
    monkeypatch.setenv("LABCAL_CONFIG", str(lab))
    monkeypatch.setenv("LABCAL_STATION", BENCH)


def test_an_attended_run_notifies_each_remount_naming_the_bench_run_serial_and_page(tmp_path, capsys,
                                                                                   monkeypatch):
    """`labcal run --sim` answered from a file (someone confirms each mount): one notification per
    mount of four-mount-64 (the plan's order in a first replicate), each naming the bench as
    $LABCAL_STATION does (a dry run marked so), the run's number, the serial, and linking to the run's
    page under the lab file's server_url; then "finished" with the verdict and the fit's residual
    standard errors as the run's fit.json states them."""
    plan, _ = load_plan("four-mount-64")
    lab_file(tmp_path, monkeypatch)
    answers = tmp_path / "answers.txt"
    answers.write_text("y\n" * len(plan.mounts), encoding="utf-8")
    with endpoint() as (url, inbox):
        monkeypatch.setenv("LABCAL_NOTIFY", url)
        code, out, err = cli(capsys, "run", "--sim", "--answers", str(answers), "--no-report", "--plan",
                             "four-mount-64", "--serial", "ACC-0042", "--out", str(tmp_path / "run"),
                             "--json")
        assert code == 0, err
        run_id = json.loads(out)["run_id"]
        bodies = inbox.wait_for(len(plan.mounts) + 1)  # close() drained the queue: all are in already
    assert len(bodies) == len(plan.mounts) + 1, bodies
    who = f"labcal {BENCH} (simulated), run {run_id} (ACC-0042): "
    page = f"\n{SERVER_URL}/runs/{run_id}"
    for step, ((y, u), body) in enumerate(zip(plan.mounts, bodies, strict=False), 1):
        assert body.startswith(who) and body.endswith(page), body
        assert f"mount {step} of {len(plan.mounts)}: remount the instrument on the {described(y, u)}" in body
    fit = json.loads((tmp_path / "run" / "fit.json").read_text())
    rse = ", ".join(f"{axis} {value * 1e3:.3g} mV"
                    for axis, value in zip("xyz", fit["residual_standard_error"], strict=True))
    n = plan.n_points
    assert bodies[-1] == (f"{who}finished: complete, {n} of {n} points; {fit['model']} fit of {n} points: "
                          f"residual standard error {rse}{page}")
    titles = [doc["title"] for doc in inbox.received]
    assert titles[-1] == f"labcal run {run_id} on {BENCH}: finished, complete"
    assert "notification" not in err  # every one was sent: nothing to warn of


def test_an_unattended_run_asks_nobody_for_a_remount(tmp_path, capsys, monkeypatch):
    """`labcal run --sim --yes`: the rig remounts itself, so the only notification is the run's end
    (no link: the lab file gives no server address)."""
    lab_file(tmp_path, monkeypatch)
    (tmp_path / "lab.toml").write_text("", encoding="utf-8")  # a lab file without server_url
    with endpoint() as (url, inbox):
        monkeypatch.setenv("LABCAL_NOTIFY", url)
        code, out, err = cli(capsys, "run", "--sim", "--yes", "--no-report", "--plan", "four-mount-64",
                             "--out", str(tmp_path / "run"), "--json")
        assert code == 0, err
        bodies = inbox.wait_for(1)
    run_id = json.loads(out)["run_id"]
    assert len(bodies) == 1, bodies
    who = f"labcal {BENCH} (simulated), run {run_id}: "
    assert bodies[0].startswith(f"{who}finished: complete, 64 of 64 points"), bodies
    assert "remount" not in bodies[0] and "http" not in bodies[0]


def test_a_fault_pause_is_notified_with_the_fault(tmp_path, capsys, monkeypatch, no_leaks):  # noqa: F811
    """The roll drive of an emulated AZ station raises alarm 10h mid-run (AZ manual: excessive
    position deviation); the run pauses and the notification says "paused" with the alarm; the
    operator aborts, and the end is "stopped" with why and how to continue."""
    alarm = '\n[[emulation.faults]]\ndevice = "roll"\nkind = "alarm"\ncode = 16\nafter = 150\n'
    station = private_file("az-modbus-rtu", tmp_path, alarm, "timeout_s = 0.1\nreconnect_s = 1")
    answers = tmp_path / "answers.txt"
    answers.write_text("y\ny\ny\ny\na\n")
    monkeypatch.setenv("LABCAL_STATION", BENCH)
    with endpoint() as (url, inbox):
        monkeypatch.setenv("LABCAL_NOTIFY", url)
        code, _, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--answers", str(answers),
                           "--out", str(tmp_path / "run"))
        bodies = inbox.bodies()
    assert code == 1, err
    run_id = json.loads((tmp_path / "run" / "run.json").read_text())["run_id"]
    who = f"labcal {BENCH} (simulated), run {run_id}: "  # the bench, not its station file
    paused = [b for b in bodies if b.startswith(f"{who}paused (fault: ")]
    assert len(paused) == 1, bodies
    assert "roll table" in paused[0] and "alarm 10h (excessive position deviation)" in paused[0]
    assert bodies[-1].startswith(f"{who}finished: stopped (operator aborted the run after a pause (fault: ")
    assert bodies[-1].endswith(f"; labcal resume {tmp_path / 'run'} continues it")
    assert all(b.startswith(who) for b in bodies)


@contextmanager
def garbage_endpoint() -> Iterator[int]:
    """A TCP port that answers any request with bytes that are not HTTP, then hangs up."""
    server = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve() -> None:
        server.settimeout(0.1)
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            with conn:
                conn.recv(65536)
                conn.sendall(b"\x00\xffnot http at all\r\n\r\n")

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1]
    finally:
        stop.set()
        thread.join(5)
        server.close()


@pytest.mark.parametrize("where", ["closed port", "not HTTP"])
def test_an_endpoint_that_fails_costs_the_run_nothing_and_says_so_once(where, tmp_path, capsys, monkeypatch):
    """Every notification fails (a closed port: refused; an endpoint answering garbage): the run
    completes, every point of the plan is in the journal, and stderr has one warning line."""
    plan, _ = load_plan("four-mount-64")
    with garbage_endpoint() as garbage:
        port = free_port() if where == "closed port" else garbage  # free_port's socket is closed again
        monkeypatch.setenv("LABCAL_NOTIFY", f"json://127.0.0.1:{port}/")
        code, out, err = cli(capsys, "run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "run"),
                             "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["points"] == plan.n_points
    assert journaled_points(tmp_path / "labcal.sqlite", summary["run_id"]) == plan.n_points
    assert json.loads((tmp_path / "run" / "run.json").read_text())["status"] == "complete"
    warnings = [line for line in err.splitlines() if "notification" in line]
    assert len(warnings) == 1, err
    assert warnings[0].startswith("notification not sent (the end)") and "the run goes on" in warnings[0]


@pytest.mark.parametrize("given", ["env", "lab file"])
def test_a_url_apprise_cannot_parse_is_refused_before_anything_moves(given, tmp_path, capsys, monkeypatch):
    """A second URL with a scheme apprise has no plugin for: exit 2, one line naming where it came
    from and which URL (its scheme only: URLs hold tokens), no run folder, nothing journaled."""
    with endpoint() as (url, inbox):
        if given == "env":
            monkeypatch.setenv("LABCAL_NOTIFY", f"{url}, nosuchservice://token@host")
            source = "$LABCAL_NOTIFY"
        else:
            lab = tmp_path / "lab.toml"
            lab.write_text(f'notify = ["{url}", "nosuchservice://token@host"]\n')
            monkeypatch.setenv("LABCAL_CONFIG", str(lab))
            source = f"{lab}: notify"
        code, out, err = cli(capsys, "run", "--sim", "--yes", "--out", str(tmp_path / "run"))
    assert code == 2 and out == ""
    assert err.strip().count("\n") == 0, err
    assert f"{source}: URL 2 of 2 (nosuchservice://…) is not a notification URL apprise understands" in err
    assert "token" not in err
    assert not (tmp_path / "run").exists() and not (tmp_path / "labcal.sqlite").exists()
    assert inbox.received == []


def test_close_waits_a_bounded_time_for_an_endpoint_that_never_answers(tmp_path):
    """An endpoint that takes the connection and never replies holds the worker in its send; the
    run's thread queues at once, and close gives up after its drain bound and names what was left."""
    warned: list[str] = []
    release = threading.Event()
    server = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []

    def accept() -> None:
        conn, _ = server.accept()
        held.append(conn)
        release.wait(30)

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        notes = Notifications([f"json://127.0.0.1:{server.getsockname()[1]}/"], "test", warned.append,
                              drain_s=0.3)
        for what in ("mount 1 of 2", "the end"):
            notes.send(Message(what, what, f"body of {what}"))
        notes.close()  # returns although the worker is still held in its send (apprise's read timeout: 4 s)
        said = list(warned)  # what close said; the held send fails later, once the endpoint is let go
    finally:
        release.set()
        thread.join(5)
        for conn in held:
            conn.close()
        server.close()
    assert said == ["notifications not sent: 2 still queued or unanswered after 0.3 s "
                    "(mount 1 of 2, the end)"]


def test_without_apprise_a_run_goes_on_and_says_so_once(tmp_path, capsys, monkeypatch):
    """apprise not installed (its import fails, as it does without the `lab` extra): the run is
    complete with every point, and one line says the notifications are off and how to get them."""
    import sys

    monkeypatch.setitem(sys.modules, "apprise", None)  # `import apprise` raises ImportError
    monkeypatch.setenv("LABCAL_NOTIFY", f"json://127.0.0.1:{free_port()}/")
    code, out, err = cli(capsys, "run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16",
                         "--out", str(tmp_path / "run"), "--json")
    assert code == 0, err
    assert json.loads(out)["points"] == 16 == len(load_plan("one-mount-16")[0].points)
    warnings = [line for line in err.splitlines() if "notification" in line]
    assert warnings == ["notifications are off: $LABCAL_NOTIFY names notification URLs, but apprise is not "
                        "installed (pip install 'labcal[lab]'); the run goes on without them"], err


def test_a_run_stopped_at_a_remount_and_resumed_notifies_under_its_own_number(tmp_path, capsys, monkeypatch):
    """`labcal run --sim` stopped at the second remount prompt ("stop"): "finished: stopped" with how to
    go on; `labcal resume` of that folder asks for the mount again (to confirm it), then the rest
    of the plan's mounts, and ends "finished: complete" — every notification under the one run's
    number."""
    plan, _ = load_plan("four-mount-64")
    answers = tmp_path / "answers.txt"
    answers.write_text("y\nstop\n")
    run_dir = tmp_path / "run"
    monkeypatch.setenv("LABCAL_STATION", BENCH)
    with endpoint() as (url, inbox):
        monkeypatch.setenv("LABCAL_NOTIFY", url)
        code, _, err = cli(capsys, "run", "--sim", "--answers", str(answers), "--no-report",
                           "--out", str(run_dir))
        assert code == 1, err
        first = len(inbox.received)
        stopped = json.loads((run_dir / "run.json").read_text())  # the run's own record of how it ended
        answers.write_text("y\n" * len(plan.mounts), encoding="utf-8")  # someone confirms each mount
        code, _, err = cli(capsys, "resume", str(run_dir), "--answers", str(answers), "--no-report")
        assert code == 0, err
        bodies = inbox.bodies()
    run_id = json.loads((run_dir / "run.json").read_text())["run_id"]
    who = f"labcal {BENCH} (simulated), run {run_id}: "
    assert all(b.startswith(who) for b in bodies), bodies
    n = len(plan.mounts)
    (y1, u1), (y2, u2) = plan.mounts[:2]
    assert bodies[:first] == [
        f"{who}mount 1 of {n}: remount the instrument on the {described(y1, u1)}; the tables wait until the "
        "operator confirms it at the station",
        f"{who}mount 2 of {n}: remount the instrument on the {described(y2, u2)}; the tables wait until the "
        "operator confirms it at the station",
        f"{who}finished: stopped ({stopped['reason']}), {stopped['points_recorded']} of {plan.n_points} "
        f"points; labcal resume {run_dir} continues it"]
    assert stopped["status"] == "stopped" and stopped["points_recorded"] == len(plan.points)  # one mount's
    mounts = [b for b in bodies[first:] if "remount the instrument" in b]
    assert len(mounts) == n - 1 and all(f"{who}mount {step} of {n}: " in b
                                        for step, b in zip(range(2, n + 1), mounts, strict=True)), mounts
    assert bodies[-1].startswith(f"{who}finished: complete, {plan.n_points} of {plan.n_points} points; ")


def test_what_a_pause_and_the_ends_say():
    """The words of a pause whose stop failed, and of the ends that are not complete, from events
    made here: the reasons and counts come through as given, with how to continue where one can."""
    from labcal.run.events import Paused, Status
    from labcal.run.notify import RunName, RunNotifier

    notifier = RunNotifier(Notifications([], "test", print), RunName("bench-2"), Path("/srv/runs/r7"))
    who = "labcal bench-2, run 7: "
    paused = notifier.compose(Paused(run_id=7, rig_time_s=5.0, why="fault: roll table: no reply",
                                     may_be_moving=("roll",)))
    assert paused is not None and paused.body == (
        f"{who}paused (fault: roll table: no reply); the stop did not reach the roll table(s): it may still "
        "be moving; every reading so far is saved, and the run waits for the operator to resume or abort it "
        "at the station")
    ends = {status: notifier.compose(Status(run_id=7, rig_time_s=9.0, status=status, reason=reason, at="end",
                                            points_done=10, points_total=64))
            for status, reason in (("interrupted", "SIGTERM"), ("failed", "finished without enough good "
                                                                          "points to fit"))}
    assert ends["interrupted"] is not None and ends["interrupted"].body == (
        f"{who}finished: interrupted (SIGTERM), 10 of 64 points; labcal resume /srv/runs/r7 continues it")
    assert ends["failed"] is not None and ends["failed"].body == (
        f"{who}finished: failed (finished without enough good points to fit), 10 of 64 points")
    for at in ("start", "point", "mount", "resume"):  # a run going on is no news
        assert notifier.compose(Status(run_id=7, rig_time_s=1.0, status="running", at=at, points_done=1,
                                       points_total=64)) is None


def test_a_run_links_to_its_page_only_once_the_lab_has_numbered_it():
    """A run the lab has numbered links to /runs/NUMBER under the server's address (a trailing slash
    or not); a provisional label (8 hex digits of the uuid, until the bench reaches the lab) names no
    page; without server_url there is no link."""
    from labcal.run.notify import RunName

    assert RunName("bench-2", "ACC-1", "https://lab.example.org/").link("17") == "https://lab.example.org/runs/17"
    assert RunName("bench-2", None, "http://10.0.0.5:8024").link("3") == "http://10.0.0.5:8024/runs/3"
    assert RunName("bench-2", None, "https://lab.example.org").link("0c1f9a2e (provisional)") is None
    assert RunName("bench-2").link("17") is None
    named = RunName("bench-2", "ACC-1", simulated=True).who("17")
    assert named == "labcal bench-2 (simulated), run 17 (ACC-1)"


def test_a_server_url_that_is_not_a_web_address_is_refused_before_anything_moves(tmp_path, capsys,
                                                                                 monkeypatch):
    lab_file(tmp_path, monkeypatch, server_url="lab.example.org")  # no scheme: no link could work
    code, out, err = cli(capsys, "run", "--sim", "--yes", "--out", str(tmp_path / "run"))
    assert code == 2 and out == ""
    assert err.strip().count("\n") == 0 and "server_url" in err, err
    assert not (tmp_path / "run").exists()
