"""The lab under load: paced stations into one server and one PostgreSQL, polled 10×/s.

What it sets up, all on this machine and on 127.0.0.1 only:
- a private PostgreSQL cluster (tests/services.py's `Cluster`: initdb into a temporary folder, as the
  ``postgres`` user when run as root), `labcal db upgrade`, a viewer (`labcal user add … --json`: its
  API token) and `labcal serve --port 0`;
- ``--stations`` (default 8) `labcal run --sim --yes --no-report --pace X --plan PLAN` processes at
  once, each with its own journal (``LABCAL_JOURNAL``) and name (``LABCAL_STATION`` bench-1 …
  bench-N), all with the same ``LABCAL_DB`` URL: each journals locally and its sender pushes every
  record to PostgreSQL (labcal/store/sync.py), which the server reads;
- meanwhile a client polls the API at ``--rate`` (default 10) requests per second in all, open loop
  (a request leaves on schedule whether or not the one before has come back, so a slow answer does
  not hide the ones behind it): ``GET /api/runs``, then ``GET /api/runs/{id}`` of each run it
  lists, round and round, until every station has exited (or ``--limit`` seconds have passed: the
  stations are then stopped and the benchmark fails); with ``--sse`` it also holds one event stream
  (``/api/runs/{id}/stream``) per run and counts the points each brings.

The floor: as soon as the lab server has answered, the same client sends the same request to a
trivial HTTP server too (http.server in a process of its own, HTTP/1.1 keep-alive like uvicorn),
which answers a fixed JSON body of the size of the lab server's answer. Both see the same machine,
the same stations and the same client at the same moments, so the ratio of the two latencies is
the lab server's own cost.

Then two figures that tell the server's cost apart from the machine's: the CPU time `labcal serve`
used while the stations ran (per request), and, once they have finished, ``--quiet`` (30) requests
of each kind one at a time, each with its floor.

The report: requests made, latency p50/p95/p99/max of each (and the ratios), errors (an answer
other than 200, or none within ``--timeout``), each run's wall time against its rig time / X (the
journal's own clocks: ``runs.started_utc``→``ended_utc`` against the last rig time it journaled), and
the readings lost or doubled: every station's journal read with sqlite3, PostgreSQL read with
psycopg, each (run uuid, seq) compared column by column. Lost, doubled, different or unexpected
readings, a failed station, or a request error make the exit status 1.

Defaults: 8 stations, plan four-mount-64 (1960 rig seconds), pace 30 (65 s of wall time per run),
10 requests/s, 5 s timeout, no streams: 1.5 to 2 minutes in all on a busy two-core machine.

Usage: python benchmarks/lab_load.py [--stations 8] [--plan four-mount-64] [--pace 30] [--rate 10]
       [--sse] [--timeout 5] [--limit 600] [--json]
Needs the lab extra (pip install -e '.[lab,test]') and Debian's postgresql package.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from contextlib import closing
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from lab_readings import journal_points, server_points  # noqa: E402  (sqlite3 and psycopg, not labcal)
from services import Cluster  # noqa: E402  (the test suite's private PostgreSQL)

LABCAL = str(Path(sys.executable).with_name("labcal"))
ENV = {k: v for k, v in os.environ.items() if not k.startswith("LABCAL_")}

FLOOR_SERVER = r"""
import sys
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

class Fixed(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"  # keep-alive, as uvicorn does
    disable_nagle_algorithm = True  # TCP_NODELAY, as asyncio (uvicorn) sets it

    def do_GET(self):
        size = int(parse_qs(urlsplit(self.path).query).get("size", ["2"])[0])
        body = b'{"pad":"' + b"x" * max(0, size - 10) + b'"}'
        head = f"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
        self.wfile.write(head.encode() + body)  # one write: headers and body in the same segments

    def log_message(self, *args):
        pass

server = ThreadingHTTPServer(("127.0.0.1", 0), Fixed)
print(f"http://127.0.0.1:{server.server_port}", flush=True)
try:
    server.serve_forever()
except KeyboardInterrupt:
    pass
"""


@dataclass
class Requests:
    """What one side (the lab server or the floor) answered."""

    latencies: list[float] = field(default_factory=list)  # seconds, answers with status 200
    by_kind: dict[str, list[float]] = field(default_factory=dict)  # the same, per request kind
    sizes: dict[str, list[int]] = field(default_factory=dict)  # bytes of each answer, per kind
    non_200: dict[int, int] = field(default_factory=dict)
    timeouts: int = 0
    failures: list[str] = field(default_factory=list)  # connection errors and the like, each said

    @property
    def made(self) -> int:
        return len(self.latencies) + sum(self.non_200.values()) + self.timeouts + len(self.failures)

    @property
    def errors(self) -> int:
        return self.made - len(self.latencies)

    def figures(self) -> dict[str, Any]:
        ms = np.array(self.latencies) * 1e3 if self.latencies else np.array([np.nan])
        return {"requests": self.made, "errors": self.errors,
                "non_200": {str(k): v for k, v in self.non_200.items()}, "timeouts": self.timeouts,
                "failures": self.failures[:5],
                "p50_ms": float(np.percentile(ms, 50)), "p95_ms": float(np.percentile(ms, 95)),
                "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max()),
                "by_request": {kind: {"requests": len(values),
                                      "p50_ms": float(np.percentile(values, 50)) * 1e3,
                                      "p95_ms": float(np.percentile(values, 95)) * 1e3,
                                      "mean_bytes": float(np.mean(self.sizes[kind])) if kind in self.sizes
                                      else None}
                               for kind, values in self.by_kind.items()}}


def call(command: list[str], env: dict[str, str] | None = None) -> str:
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, env=env or ENV)
    if done.returncode:
        raise SystemExit(f"{' '.join(command[:3])} failed: {done.stderr.strip()[-500:]}")
    return done.stdout


def first_url(process: subprocess.Popen, what: str) -> str:
    """The URL a server prints on its first line."""
    assert process.stdout is not None
    line = process.stdout.readline()
    found = re.search(r"http://127\.0\.0\.1:\d+", line)
    if not found:
        raise SystemExit(f"{what} printed {line!r} instead of its URL")
    return found[0]


def stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.communicate()


async def poll(url: str, floor: str, token: str, stations: list[subprocess.Popen], rate: float,
               timeout_s: float, limit_s: float, sse: bool
               ) -> tuple[Requests, Requests, dict[int, list[int]], bool]:
    """The client: requests on schedule until every station has exited (True) or ``limit_s`` (False).
    Each goes to the lab server and, with the size of its answer, to the floor."""
    lab, bare = Requests(), Requests()
    streamed: dict[int, list[int]] = {}
    ids: list[int] = []
    headers = {"Authorization": f"Bearer {token}"}
    # An idle pooled connection is dropped by the client after 2 s, before uvicorn's own 5 s
    # keep-alive timeout closes it: at httpx's default (5 s, the same) a request sometimes went out
    # on a connection the server was closing at that moment and failed (ReadError), which is the
    # client's race, not the server's fault. Any error left is the server's.
    limits = httpx.Limits(max_connections=100, max_keepalive_connections=20, keepalive_expiry=2.0)
    tasks: set[asyncio.Task] = set()
    streams: dict[int, asyncio.Task] = {}

    async def one(client: httpx.AsyncClient, path: str) -> None:
        size = 2
        kind = "/api/runs" if path == "/api/runs" else "/api/runs/{id}"
        t0 = time.perf_counter()
        try:
            answer = await client.get(url + path, headers=headers)
            elapsed = time.perf_counter() - t0
            if answer.status_code != 200:
                lab.non_200[answer.status_code] = lab.non_200.get(answer.status_code, 0) + 1
            else:
                lab.latencies.append(elapsed)
                lab.by_kind.setdefault(kind, []).append(elapsed)
                size = len(answer.content)
                lab.sizes.setdefault(kind, []).append(size)
                if path == "/api/runs":
                    ids[:] = sorted(run["id"] for run in answer.json()["runs"])
        except httpx.TimeoutException:
            lab.timeouts += 1
        except httpx.HTTPError as error:
            lab.failures.append(f"{path}: {type(error).__name__}: {error}")
        t0 = time.perf_counter()
        try:
            answer = await client.get(f"{floor}{path}?size={size}")
            if answer.status_code != 200:
                bare.non_200[answer.status_code] = bare.non_200.get(answer.status_code, 0) + 1
            else:
                bare.latencies.append(time.perf_counter() - t0)
                bare.by_kind.setdefault(kind, []).append(bare.latencies[-1])
        except httpx.TimeoutException:
            bare.timeouts += 1
        except httpx.HTTPError as error:
            bare.failures.append(f"{path}: {type(error).__name__}: {error}")

    async def stream(client: httpx.AsyncClient, run_id: int) -> None:
        """Points of one run's event stream, by seq, until cancelled."""
        seqs = streamed.setdefault(run_id, [])
        kind = "message"
        try:
            async with client.stream("GET", f"{url}/api/runs/{run_id}/stream", headers=headers,
                                     timeout=httpx.Timeout(timeout_s, read=None)) as answer:
                async for line in answer.aiter_lines():
                    if line.startswith("event:"):
                        kind = line.partition(":")[2].strip()
                    elif line.startswith("data:") and kind == "point":
                        seqs.append(int(json.loads(line.partition(":")[2])["seq"]))
                    elif line == "":
                        kind = "message"
        except httpx.HTTPError as error:
            lab.failures.append(f"stream of run {run_id}: {type(error).__name__}: {error}")

    async with httpx.AsyncClient(timeout=timeout_s, limits=limits) as client, \
            httpx.AsyncClient(timeout=None, limits=limits) as streaming:
        start = time.perf_counter()
        n, turn = 0, 0
        all_done = False
        while True:
            if all(s.poll() is not None for s in stations):
                all_done = True
                break
            if time.perf_counter() - start > limit_s:
                break
            targets = ["/api/runs"] + [f"/api/runs/{i}" for i in ids]
            path = targets[turn % len(targets)]
            turn = 0 if turn + 1 >= len(targets) else turn + 1
            task = asyncio.create_task(one(client, path))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
            if sse:
                for run_id in ids:
                    if run_id not in streams:
                        streams[run_id] = asyncio.create_task(stream(streaming, run_id))
            n += 1
            await asyncio.sleep(max(0.0, start + n / rate - time.perf_counter()))
        if tasks:
            await asyncio.wait(tasks)
        await asyncio.sleep(3.0 if sse else 0.0)  # the last points reach the streams (server --poll 0.5)
        for task in streams.values():
            task.cancel()
        await asyncio.gather(*streams.values(), return_exceptions=True)
    return lab, bare, streamed, all_done


def readings(url: str, journals: list[Path]) -> dict[str, int]:
    """Lost (journaled, not in PostgreSQL), doubled (there more than once), different (there, not equal)
    and unexpected (there, in no journal) readings."""
    expected: dict[tuple[str, int], tuple] = {}
    for journal in journals:
        expected.update(journal_points(journal))
    return compare(expected, server_points(url))


def compare(expected: dict[tuple[str, int], tuple], found: list[tuple]) -> dict[str, int]:
    """The counts of `readings`: ``expected`` keyed by (run uuid, seq) with the point's columns from
    seq on, ``found`` the server's rows (run uuid, then the same columns)."""
    seen: dict[tuple[str, int], int] = {}
    different = 0
    for row in found:
        key = (row[0], row[1])
        seen[key] = seen.get(key, 0) + 1
        if key in expected and row[1:] != expected[key]:
            different += 1
    return {"journaled": len(expected), "in_postgresql": len(found),
            "lost": sum(1 for key in expected if key not in seen),
            "doubled": sum(count - 1 for count in seen.values()),
            "different": different, "unexpected": sum(1 for key in seen if key not in expected)}


def cpu_seconds(pid: int) -> float:
    """User and system CPU time a process has used so far (/proc: Linux)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def quiet(url: str, floor: str, token: str, n: int) -> dict[str, dict[str, float]]:
    """Once the stations have finished: ``n`` requests of each kind one at a time, each followed by
    the floor's of the same size, so the server's cost per request shows without the stations'
    load (the machine's other users remain)."""
    headers = {"Authorization": f"Bearer {token}"}
    times: dict[str, list[float]] = {"/api/runs": [], "/api/runs/{id}": [], "floor /api/runs": [],
                                     "floor /api/runs/{id}": []}
    with httpx.Client(timeout=30) as client:
        ids = [run["id"] for run in client.get(url + "/api/runs", headers=headers).json()["runs"]]
        if not ids:
            return {}
        for i in range(n):
            one = f"/api/runs/{ids[i % len(ids)]}"
            for kind, path in (("/api/runs", "/api/runs"), ("/api/runs/{id}", one)):
                t0 = time.perf_counter()
                answer = client.get(url + path, headers=headers)
                times[kind].append(time.perf_counter() - t0)
                answer.raise_for_status()
                t0 = time.perf_counter()
                client.get(f"{floor}{path}?size={len(answer.content)}").raise_for_status()
                times["floor " + kind].append(time.perf_counter() - t0)
    return {kind: {"p50_ms": float(np.percentile(v, 50)) * 1e3, "p95_ms": float(np.percentile(v, 95)) * 1e3}
            for kind, v in times.items()}


def utc(text: str) -> datetime:
    return datetime.fromisoformat(text)


def paces(journals: list[Path], pace: float) -> list[dict[str, Any]]:
    """Each run's wall time (its journal's started→ended UTC) against its rig time / pace (the last
    rig time the journal holds: a point's end or an event)."""
    found = []
    for journal in journals:
        with closing(sqlite3.connect(journal)) as db:
            for run_id, station, started, ended, status in db.execute(
                    "SELECT id, station, started_utc, ended_utc, status FROM runs"):
                rig = db.execute("SELECT max(m) FROM (SELECT max(t_end) AS m FROM points WHERE run_id = ? "
                                 "UNION ALL SELECT max(station_time) FROM events WHERE run_id = ?)",
                                 (run_id, run_id)).fetchone()[0] or 0.0
                wall = (utc(ended) - utc(started)).total_seconds() if ended else float("nan")
                found.append({"station": station or journal.parent.name, "status": status, "rig_s": rig,
                              "paced_s": rig / pace, "wall_s": wall,
                              "ratio": wall / (rig / pace) if rig else None})
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--stations", type=int, default=8)
    parser.add_argument("--plan", default="four-mount-64")
    parser.add_argument("--pace", type=float, default=30.0)
    parser.add_argument("--rate", type=float, default=10.0, help="API requests per second, in all")
    parser.add_argument("--sse", action="store_true", help="also hold one event stream per run")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds a request may take")
    parser.add_argument("--limit", type=float, default=600.0, help="seconds the stations may take")
    parser.add_argument("--quiet", type=int, default=30,
                        help="requests of each kind one at a time once the stations have finished")
    parser.add_argument("--json", action="store_true")
    options = parser.parse_args(argv)
    began = time.perf_counter()
    load_before = os.getloadavg()[0]
    cluster = Cluster()
    processes: list[subprocess.Popen] = []
    try:
        with tempfile.TemporaryDirectory(prefix="labcal-load-") as folder:
            work = Path(folder)
            url = cluster.url(cluster.create_database())
            (work / "lab.toml").write_text("")
            call([LABCAL, "db", "upgrade", "--db", url])
            token = json.loads(call([LABCAL, "user", "add", "bench-viewer", "--role", "viewer", "--db", url,
                                     "--json"], {**ENV, "LABCAL_PASSWORD": "load bench passphrase"}))["token"]
            server = subprocess.Popen([LABCAL, "serve", "--port", "0", "--db", url], stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, env=ENV)
            processes.append(server)
            lab_url = first_url(server, "labcal serve")
            floor_server = subprocess.Popen([sys.executable, "-c", FLOOR_SERVER], stdout=subprocess.PIPE,
                                            text=True, env=ENV)
            processes.append(floor_server)
            floor_url = first_url(floor_server, "the floor server")
            names = [f"bench-{n + 1}" for n in range(options.stations)]
            journals = [work / name / "journal.sqlite" for name in names]
            stations = []
            for n, name in enumerate(names):
                env = {**ENV, "LABCAL_DB": url, "LABCAL_JOURNAL": str(work / name / "journal.sqlite"),
                       "LABCAL_STATION": name, "LABCAL_CONFIG": str(work / "lab.toml"),
                       "XDG_DATA_HOME": str(work / name / "data")}
                stations.append(subprocess.Popen(
                    [LABCAL, "run", "--sim", "--yes", "--no-report", "--pace", f"{options.pace:g}",
                     "--plan", options.plan, "--seed", str(n + 1), "--out", str(work / name / "run")],
                    env=env, stdout=subprocess.DEVNULL, stderr=(work / f"{name}.err").open("w")))
            processes.extend(stations)
            cpu_before, load_began = cpu_seconds(server.pid), time.perf_counter()
            lab, bare, streamed, all_done = asyncio.run(poll(lab_url, floor_url, token, stations,
                                                             options.rate, options.timeout, options.limit,
                                                             options.sse))
            failed = []
            for name, station in zip(names, stations, strict=True):
                stop(station)
                stderr = (work / f"{name}.err").read_text()
                if station.returncode or "not yet in the lab database" in stderr or "unreachable" in stderr:
                    failed.append(f"{name}: exit {station.returncode}: {stderr.strip()[-300:]}")
            server_cpu = {"cpu_s": cpu_seconds(server.pid) - cpu_before,
                          "wall_s": time.perf_counter() - load_began}
            counted = readings(url, [j for j in journals if j.exists()])
            cpu_before = cpu_seconds(server.pid)
            one_at_a_time = quiet(lab_url, floor_url, token, options.quiet)
            if one_at_a_time:
                one_at_a_time["server_cpu_ms_per_request"] = {
                    "mean_ms": 1e3 * (cpu_seconds(server.pid) - cpu_before) / (2 * options.quiet + 1)}
            runs = paces([j for j in journals if j.exists()], options.pace)
            points_streamed = {str(k): {"points": len(v), "distinct": len(set(v))}
                               for k, v in streamed.items()}
    finally:
        for process in processes:
            stop(process)
        cluster.stop()
    lab_f, bare_f = lab.figures(), bare.figures()
    ratios = {q: lab_f[f"{q}_ms"] / bare_f[f"{q}_ms"] for q in ("p50", "p95", "p99", "max")}
    pace_ratios = [r["ratio"] for r in runs if r["ratio"] is not None]
    result = {
        "stations": options.stations, "plan": options.plan, "pace": options.pace, "rate": options.rate,
        "sse": options.sse, "wall_s": time.perf_counter() - began, "cores": os.cpu_count(),
        "load_1min": {"before": load_before, "after": os.getloadavg()[0]}, "all_done_within_limit": all_done,
        "stations_failed": failed, "lab_server": lab_f, "floor": bare_f, "ratio": ratios,
        "runs": runs, "pace_ratio_max": max(pace_ratios, default=None), "readings": counted,
        "streamed": points_streamed, "server_cpu": server_cpu, "one_at_a_time": one_at_a_time,
    }
    bad = (counted["lost"] or counted["doubled"] or counted["different"] or counted["unexpected"] or failed
           or not all_done or lab.errors or len(runs) != options.stations)
    if options.json:
        print(json.dumps(result, indent=2))
    else:
        report(result)
    return 1 if bad else 0


def report(r: dict[str, Any]) -> None:
    lab, floor, ratio, c = r["lab_server"], r["floor"], r["ratio"], r["readings"]
    print(f"{r['stations']} stations, {r['plan']} at pace {r['pace']:g}, API polled {r['rate']:g}/s"
          f"{' with one event stream per run' if r['sse'] else ''}: {r['wall_s']:.0f} s in all; "
          f"{r['cores']} cores, load average {r['load_1min']['before']:.1f} before, "
          f"{r['load_1min']['after']:.1f} after")
    for name, f in (("lab server", lab), ("floor", floor)):
        print(f"  {name:10} {f['requests']} requests, p50 {f['p50_ms']:.1f} ms, p95 {f['p95_ms']:.1f} ms, "
              f"p99 {f['p99_ms']:.1f} ms, max {f['max_ms']:.1f} ms; errors {f['errors']} "
              f"(non-200 {sum(f['non_200'].values())}, timeouts {f['timeouts']})")
        for kind, k in f["by_request"].items():
            size = f", {k['mean_bytes']:.0f} bytes on average" if k["mean_bytes"] else ""
            print(f"    {kind:14} {k['requests']} requests, p50 {k['p50_ms']:.1f} ms, "
                  f"p95 {k['p95_ms']:.1f} ms{size}")
        for failure in f["failures"]:
            print(f"    {failure}")
    print(f"  ratio      p50 {ratio['p50']:.1f}×, p95 {ratio['p95']:.1f}×, p99 {ratio['p99']:.1f}×, "
          f"max {ratio['max']:.1f}× the floor (http.server, fixed JSON of the same size)")
    for run in r["runs"]:
        print(f"  {run['station']}: {run['status']}, wall {run['wall_s']:.1f} s for {run['rig_s']:.0f} rig s "
              f"/ {r['pace']:g} = {run['paced_s']:.1f} s ({run['ratio']:.2f}×)")
    print(f"  readings: {c['journaled']} journaled, {c['in_postgresql']} in PostgreSQL; lost {c['lost']}, "
          f"doubled {c['doubled']}, different {c['different']}, unexpected {c['unexpected']}")
    cpu = r["server_cpu"]
    print(f"  labcal serve used {cpu['cpu_s']:.1f} CPU s in {cpu['wall_s']:.0f} s "
          f"({100 * cpu['cpu_s'] / cpu['wall_s']:.0f} % of a core), "
          f"{1e3 * cpu['cpu_s'] / max(1, lab['requests']):.0f} ms per request")
    q = r["one_at_a_time"]
    if q:
        print("  after the runs, one request at a time: " + "; ".join(
            f"{kind} p50 {q[kind]['p50_ms']:.1f} ms (floor {q['floor ' + kind]['p50_ms']:.1f} ms), "
            f"p95 {q[kind]['p95_ms']:.1f} ms (floor {q['floor ' + kind]['p95_ms']:.1f} ms)"
            for kind in ("/api/runs", "/api/runs/{id}"))
            + f"; labcal serve's CPU {q['server_cpu_ms_per_request']['mean_ms']:.1f} ms per request (mean)")
    for run_id, s in r["streamed"].items():
        print(f"  stream of run {run_id}: {s['points']} points ({s['distinct']} distinct)")
    for failure in r["stations_failed"]:
        print(f"  FAILED {failure}")
    if not r["all_done_within_limit"]:
        print("  FAILED: the stations were still running at --limit")


if __name__ == "__main__":
    sys.exit(main())
