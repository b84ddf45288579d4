"""Expected-protocol transcripts (PyMeasure's style): a byte stream that expects exactly the bytes
a manual documents for an operation, in order, and answers each with the documented reply. No
emulator: a wrong register, scaling, terminator or reply parse fails on the first byte that
differs. Used as a `labcal.drivers.transport.Stream` (line protocols) and as the pyserial port of
pymodbus's serial client (Modbus RTU)."""

from __future__ import annotations

import time

SLICE_S = 0.005


class Transcript:
    """``[(request, reply), ...]``: each write must be the next request; its reply (b"" for
    silence) is then what reads return."""

    def __init__(self, exchanges: list[tuple[bytes, bytes]]):
        self.exchanges = list(exchanges)
        self.pending = b""
        self.is_open = True
        self.inter_byte_timeout = 0.0

    # --- what both kinds of user call -----------------------------------------------------------
    def write(self, data: bytes) -> int:
        assert self.exchanges, f"unexpected write {bytes(data)!r}: the transcript is over"
        expected, reply = self.exchanges.pop(0)
        assert bytes(data) == expected, f"wrote {bytes(data)!r}, the manual says {expected!r}"
        self.pending += reply
        return len(data)

    def close(self) -> None:
        self.is_open = False

    def done(self) -> bool:
        return not self.exchanges and not self.pending

    # --- labcal's Stream ------------------------------------------------------------------------
    def read_some(self) -> bytes:
        if not self.pending:
            time.sleep(SLICE_S)
        data, self.pending = self.pending, b""
        return data

    # --- pyserial, as pymodbus uses it ----------------------------------------------------------
    @property
    def in_waiting(self) -> int:
        return len(self.pending)

    def read(self, size: int = 1) -> bytes:
        data, self.pending = self.pending[:size], self.pending[size:]
        return data


def lines(*pairs: tuple[str, str | None], eol: str) -> list[tuple[bytes, bytes]]:
    """Line exchanges: (command, reply or None for silence), each with the protocol's terminator."""
    return [(command.encode() + eol.encode(), b"" if reply is None else reply.encode() + eol.encode())
            for command, reply in pairs]
