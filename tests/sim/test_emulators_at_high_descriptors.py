"""An emulator serves whatever its descriptors' numbers: a process holding a thousand files and
sockets (a test worker late in the suite, a long `labcal sim serve`) gives it numbers past 1024,
which `select.select` refuses ("filedescriptor out of range"); the emulator's thread died of it with
its port still open, and a run through the drivers then failed its checklist."""

from __future__ import annotations

import contextlib
import os
import resource
import select
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from labcal.sim.endpoint import Endpoint
from labcal.sim.line_server import LineServer
from labcal.sim.ptys import PtyPair

FD_SETSIZE = 1024  # select(2): "an fd_set is a fixed size buffer ... FD_SETSIZE (1024)"


class Echo:
    """A line device that answers each request with the request in capitals."""

    eol = b"\r\n"
    networked = True

    def route(self, line: str) -> str:
        return "echo"

    def handle(self, line: str) -> str | None:
        return line.upper()

    def refuse(self, line: str, code: int | str | None) -> None:
        raise AssertionError("no faults here")

    alarm = power_cycle = refuse


@pytest.fixture
def high_descriptors() -> Iterator[None]:
    """Descriptors up to past FD_SETSIZE held open, so that the next ones made are numbered above it."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    wanted = FD_SETSIZE + 64
    if hard != resource.RLIM_INFINITY and hard < wanted:
        pytest.skip(f"this process may open only {hard} files")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, wanted), hard))
    held = []
    try:
        while not held or held[-1] < FD_SETSIZE + 8:
            held.append(os.open(os.devnull, os.O_RDONLY))
        yield
    finally:
        for fd in held:
            os.close(fd)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_a_tcp_line_emulator_answers_on_descriptors_past_1024(high_descriptors):
    server = LineServer(Echo(), Endpoint("tcp", "127.0.0.1", 0), {})
    try:
        with socket.create_connection((server.endpoint.host, server.endpoint.port), timeout=5) as conn:
            assert conn.fileno() > FD_SETSIZE
            conn.sendall(b"1TP?\r\n")
            assert conn.makefile("rb").readline() == b"1TP?\r\n".upper()
        assert server.errors == []
    finally:
        server.close()


def test_a_pty_relay_carries_bytes_on_descriptors_past_1024(high_descriptors, tmp_path: Path):
    pair = PtyPair(str(tmp_path / "link"))
    try:
        with contextlib.ExitStack() as stack:
            device = os.open(pair.device_path, os.O_RDWR | os.O_NOCTTY)
            stack.callback(os.close, device)
            driver = os.open(tmp_path / "link", os.O_RDWR | os.O_NOCTTY)
            stack.callback(os.close, driver)
            assert min(device, driver) > FD_SETSIZE
            os.write(driver, b"ping\n")
            waiting = select.poll()  # select.select would refuse these descriptors itself
            waiting.register(device, select.POLLIN)
            assert waiting.poll(5000), "the relay carried nothing within 5 s"
            assert os.read(device, 64) == b"ping\n"
    finally:
        pair.close()
