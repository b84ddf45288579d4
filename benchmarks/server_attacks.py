"""The lab server under the attacks of an OWASP ASVS level-2 review: the figures, before and after.

Everything on this machine and on 127.0.0.1 only, every loop bounded. It makes a lab database in a
temporary folder (`labcal user add`: a viewer, a technician, an approver; one simulated run,
`labcal run --sim --no-report --plan one-mount-16`, for the streams), starts `labcal serve --port 0`
with an open-file limit of 1,024 (the review's machine), and measures:

1. guessing: 20 wrong passwords for the approver, then the right one — the statuses;
2. 10,000 anonymous ``GET /login`` (4 clients): is a viewer signed in before still signed in?
3. 40 concurrent ``POST /login`` (each with its own form): the server's peak RSS (VmRSS sampled
   every 20 ms) and the API's p50/p95 (``GET /api/runs``, a technician's token) meanwhile;
4. a urlencoded ``POST /login`` announcing 1 GiB: how much is sent before an answer comes, the
   answer, the peak RSS (the body is sent in 1 MiB pieces, at most ``--form-mib``);
5. 800 event streams opened by the viewer: how many were accepted, and another user's API p95 while
   they are open;
6. 1,100 connections that start a request head and never finish it: is ``GET /login`` answered
   within 2 s? (last: an old server may not recover).

The figures before are those of the code before the review's fixes, run with the same script:
``git archive <commit> | tar -x -C /tmp/base`` and ``PYTHONPATH=/tmp/base python
benchmarks/server_attacks.py --form-mib 256`` (the old server reads the whole form: 256 MiB is
enough to show it). Takes 1 to 3 minutes.

Usage: python benchmarks/server_attacks.py [--form-mib 1024] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

LABCAL = str(Path(sys.executable).with_name("labcal"))
PASSWORDS = {"vic": ("viewer", "vic's passphrase"), "tom": ("technician", "tom's passphrase"),
             "ada": ("approver", "ada's long passphrase")}


def call(*args: str) -> str:
    done = subprocess.run([LABCAL, *args], capture_output=True, text=True, timeout=300)
    if done.returncode:
        raise SystemExit(f"labcal {args[0]} failed: {done.stderr.strip()[-400:]}")
    return done.stdout


def rss_mib(pid: int) -> float:
    found = re.search(r"VmRSS:\s+(\d+) kB", Path(f"/proc/{pid}/status").read_text())
    return int(found[1]) / 1024 if found else 0.0


class Peak:
    """The server's RSS sampled every 20 ms while a block runs."""

    def __init__(self, pid: int) -> None:
        self.pid, self.peak, self._stop = pid, 0.0, threading.Event()

    def __enter__(self) -> Peak:
        def sample() -> None:
            while not self._stop.is_set():
                self.peak = max(self.peak, rss_mib(self.pid))
                time.sleep(0.02)
        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def csrf(html: str) -> str:
    return re.search(r'name="csrf" value="([^"]+)"', html)[1]


def sign_in(client: httpx.Client, name: str, password: str) -> int:
    return client.post("/login", data={"name": name, "password": password,
                                       "csrf": csrf(client.get("/login").text)}).status_code


def quantiles_ms(samples: list[float]) -> dict:
    if len(samples) < 2:
        return {"n": len(samples)}
    cut = statistics.quantiles(samples, n=20)
    return {"n": len(samples), "p50_ms": round(statistics.median(samples) * 1000, 1),
            "p95_ms": round(cut[-1] * 1000, 1), "max_ms": round(max(samples) * 1000, 1)}


def timed_gets(client: httpx.Client, path: str, n: int, timeout: float = 10.0) -> tuple[list[float], int]:
    samples, errors = [], 0
    for _ in range(n):
        began = time.perf_counter()
        try:
            ok = client.get(path, timeout=timeout).status_code == 200
        except httpx.HTTPError:
            ok = False
        samples.append(time.perf_counter() - began)
        errors += not ok
    return samples, errors


def guessing(url: str) -> dict:
    with httpx.Client(base_url=url, timeout=30) as client:
        statuses = [sign_in(client, "ada", f"guess {i}") for i in range(20)]
        right = sign_in(client, "ada", PASSWORDS["ada"][1])
    return {"wrong": {str(s): statuses.count(s) for s in sorted(set(statuses))}, "then_right": right}


def anonymous_flood(url: str) -> dict:
    viewer = httpx.Client(base_url=url, timeout=30)
    sign_in(viewer, "vic", PASSWORDS["vic"][1])

    def hammer(n: int) -> int:
        answered = 0
        with httpx.Client(base_url=url, timeout=30) as client:
            for _ in range(n):  # each a new visitor: no cookie kept from the one before
                client.cookies.clear()
                answered += client.get("/login").status_code == 200
        return answered
    began = time.monotonic()
    with ThreadPoolExecutor(4) as pool:
        answered = sum(pool.map(hammer, [2500] * 4))
    still = viewer.get("/", follow_redirects=False).status_code == 200
    viewer.close()
    return {"requests": 10_000, "answered": answered, "seconds": round(time.monotonic() - began, 1),
            "viewer_still_signed_in": still}


def crowd_of_sign_ins(url: str, pid: int, token: str) -> dict:
    forms = []
    for _ in range(40):
        client = httpx.Client(base_url=url, timeout=60)
        forms.append((client, csrf(client.get("/login").text)))
    barrier = threading.Barrier(41)
    api: list[float] = []

    def post(form: tuple[httpx.Client, str]) -> int:
        client, token_ = form
        barrier.wait()
        try:
            return client.post("/login", data={"name": "vic", "password": PASSWORDS["vic"][1],
                                               "csrf": token_}).status_code
        except httpx.HTTPError:
            return 0

    def watch() -> None:
        with httpx.Client(base_url=url, timeout=30, headers={"Authorization": f"Bearer {token}"}) as client:
            client.get("/api/runs")
            barrier.wait()
            api.extend(timed_gets(client, "/api/runs", 40)[0])
    before = rss_mib(pid)
    with Peak(pid) as peak, ThreadPoolExecutor(41) as pool:
        watching = pool.submit(watch)
        statuses = list(pool.map(post, forms))
        watching.result()
    for client, _ in forms:
        client.close()
    return {"rss_before_mib": round(before), "rss_peak_mib": round(peak.peak),
            "statuses": {str(s): statuses.count(s) for s in sorted(set(statuses))}, "api": quantiles_ms(api)}


def huge_form(url: str, pid: int, most_mib: int) -> dict:
    host, port = url.removeprefix("http://").split(":")
    head = (b"POST /login HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/x-www-form-urlencoded\r\n"
            b"Content-Length: 1073741824\r\n\r\n")
    piece = b"f=" + b"x" * (1024 * 1024 - 3) + b"&"
    sent, answer = 0, b""
    with Peak(pid) as peak, socket.create_connection((host, int(port)), timeout=30) as sock:
        sock.sendall(head)
        sock.setblocking(False)
        for _ in range(most_mib):
            try:
                answer = sock.recv(200)
                break
            except BlockingIOError:
                pass
            try:
                sock.setblocking(True)
                sock.sendall(piece)
                sent += len(piece)
                sock.setblocking(False)
            except OSError:  # the server closed it
                break
        if not answer:
            sock.setblocking(True)
            sock.settimeout(5)
            try:
                answer = sock.recv(200)
            except OSError:
                pass
    status = answer.split(b"\r\n", 1)[0].decode(errors="replace")
    return {"body_sent_mib": round(sent / 2**20), "answer": status or "none",
            "rss_peak_mib": round(peak.peak)}


def many_streams(url: str, viewer_token: str, other_token: str, budget_s: float) -> dict:
    viewer = httpx.Client(base_url=url, timeout=10, headers={"Authorization": f"Bearer {viewer_token}"},
                          limits=httpx.Limits(max_connections=None, max_keepalive_connections=0))
    opened, statuses = [], []
    try:
        began = time.monotonic()
        for _ in range(800):
            if time.monotonic() - began > budget_s:  # an old server accepts every one, ever slower
                break
            try:
                response = viewer.send(viewer.build_request("GET", "/api/runs/1/stream"), stream=True)
            except httpx.HTTPError:
                statuses.append(0)
                continue
            statuses.append(response.status_code)
            if response.status_code == 200:
                opened.append(response)
            else:
                response.close()
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {other_token}"}) as other:
            samples, errors = timed_gets(other, "/api/runs", 30)
    finally:
        for response in opened:
            response.close()
        viewer.close()
    counted = {str(s): statuses.count(s) for s in sorted(set(statuses))}
    return {"tried": len(statuses), "accepted": len(opened), "statuses": counted,
            "other_user_api": {**quantiles_ms(samples), "errors": errors}}


def half_open(url: str) -> dict:
    host, port = url.removeprefix("http://").split(":")
    held = []
    try:
        for _ in range(1100):
            sock = socket.socket()
            sock.settimeout(5)
            try:
                sock.connect((host, int(port)))
                sock.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
            except OSError:
                pass
            held.append(sock)
        began = time.monotonic()
        status: int | str
        try:
            status = httpx.get(url + "/login", timeout=2.0).status_code
        except httpx.HTTPError as exc:
            status = type(exc).__name__
        return {"connections": len(held), "answer": status, "seconds": round(time.monotonic() - began, 2)}
    finally:
        for sock in held:
            sock.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--form-mib", type=int, default=1024, help="most of the 1 GiB form to send (MiB)")
    parser.add_argument("--streams-s", type=float, default=60.0,
                        help="the most time spent opening the 800 streams (s)")
    parser.add_argument("--only", action="append", metavar="FIGURE",
                        help="measure only this (guessing, anonymous_flood, sign_in_crowd, huge_form, "
                             "streams, half_open; repeatable)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, max(soft, 4096)), hard))
    with tempfile.TemporaryDirectory(prefix="labcal-attacks-") as folder:
        db = str(Path(folder) / "lab.sqlite")
        tokens = {}
        for name, (role, password) in PASSWORDS.items():
            # --password: the one way both the old and the new `user add` take a password unasked
            out = call("user", "add", name, "--role", role, "--password", password, "--db", db, "--json")
            tokens[name] = json.loads(out)["token"]
        call("run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16", "--db", db, "--out",
             str(Path(folder) / "run"))

        def limited() -> None:
            resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 1024))
        server = subprocess.Popen([LABCAL, "serve", "--port", "0", "--db", db], stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True, preexec_fn=limited, env=os.environ)
        try:
            assert server.stdout is not None
            url = re.search(r"http://127\.0\.0\.1:\d+", server.stdout.readline())[0]
            figures = {}
            for name, measure in (
                    ("guessing", lambda: guessing(url)), ("anonymous_flood", lambda: anonymous_flood(url)),
                    ("sign_in_crowd", lambda: crowd_of_sign_ins(url, server.pid, tokens["tom"])),
                    ("huge_form", lambda: huge_form(url, server.pid, args.form_mib)),
                    ("streams", lambda: many_streams(url, tokens["vic"], tokens["tom"], args.streams_s)),
                    ("half_open", lambda: half_open(url))):
                if args.only and name not in args.only:
                    continue
                figures[name] = measure()
                if not args.json:
                    print(f"{name}: {json.dumps(figures[name])}", flush=True)
        finally:
            server.terminate()
            try:
                server.wait(15)
            except subprocess.TimeoutExpired:
                server.kill()
    if args.json:
        print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
