"""`labcal sim serve`: the emulators a station file points at, until Ctrl-C.

While they run, lines typed on standard input act on the emulated rig, as a technician's hands
and bad luck would: ``mount 180 0`` (the instrument was remounted), ``fault DEVICE KIND [COUNT]``
(e.g. ``fault pitch no-reply 3``, ``fault dmm garbled``), ``status``, ``quit``.
"""

from __future__ import annotations

import argparse
import signal
import sys

from labcal.analysis.kinematics import Mount
from labcal.commands import summary
from labcal.commands.common import SEED, TIME_SCALE, TIME_SCALE_HELP, err, out, print_json
from labcal.config.emulation import FaultKind
from labcal.config.station import load_station
from labcal.sim.emulation import Emulation
from labcal.sim.faults import Fault

HELP = ("commands: mount Y U | fault DEVICE KIND [COUNT] (KIND: no-reply, late-reply, garbled, truncated, "
        "lost-request, alarm, exception, close-port, dropped-byte) | status | quit")


def console_command(emulation, line: str) -> str:
    """Carry out one console line; returns what to print. Raises EOFError on quit."""
    words = line.split()
    if not words:
        return ""
    if words[0] in ("quit", "exit"):
        raise EOFError
    try:
        if words[0] == "mount" and len(words) == 3:
            y, u = float(words[1]), float(words[2])
            if y not in (0, 180) or u not in (0, 180):
                raise ValueError
            emulation.rig.set_mount(Mount(y, u))
            return f"instrument remounted: {Mount(y, u).describe()}"
        if words[0] == "fault" and len(words) in (3, 4) and words[1] in emulation.faults:
            fault = Fault(FaultKind(words[2]), count=int(words[3]) if len(words) == 4 else 1,
                          reopen_s=1.0 if words[2] == "close-port" else None)
            emulation.faults[words[1]].add(fault)
            return f"{words[1]}: {fault.kind} on its next {fault.count} request(s)"
        if words[0] == "status":
            rig = emulation.rig.rig
            return (f"rig time {emulation.rig.clock.now():.1f} s, pitch {rig.pitch.position():.4f}°, "
                    f"roll {rig.roll.position():.4f}°, mount {rig.mount}")
    except ValueError:
        pass
    return HELP


def cmd_serve(args: argparse.Namespace) -> int:
    config, _ = load_station(args.station)
    # Ctrl-C and a kill stop them cleanly. SIGINT is installed too: Python leaves it ignored when
    # the process started with it ignored (`labcal sim serve … &` from a script), and then nothing
    # but SIGKILL would stop the emulators.
    previous = {signum: signal.signal(signum, signal.default_int_handler)
                for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        with Emulation(config, time_scale=args.time_scale, seed=args.seed) as emulation:
            endpoints = emulation.endpoints()
            if args.json:
                print_json({"station": config.description or args.station, "time_scale": emulation.time_scale,
                            "endpoints": endpoints})
                sys.stdout.flush()
            else:
                for e in endpoints:
                    out.print(f"{' and '.join(e['devices'])}: {e['protocol']} on [bold]{e['address']}[/]")
            err.print(f"emulators running at {emulation.time_scale:g}× real time; Ctrl-C stops them. {HELP}")
            try:
                for line in sys.stdin:
                    if reply := console_command(emulation, line):
                        err.print(reply)
                while True:  # standard input closed: serve until a signal
                    signal.pause()
            except (KeyboardInterrupt, EOFError):
                pass
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    err.print("emulators stopped")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help=summary("sim"),
                       description="Emulators of the station's tables and DMM that speak the real protocols.")
    sim_sub = p.add_subparsers(dest="sim_command", required=True, metavar="SUBCOMMAND")
    serve = sim_sub.add_parser(
        "serve", help="start the emulators a station file points at, until Ctrl-C",
        description="Start the emulators a station file points at (TCP ports on loopback, pty pairs linked "
                    "where the station's ports say), print where they listen, and serve until Ctrl-C. "
                    "Then run `labcal station check` or `labcal run --station` against the same file. "
                    f"On standard input: {HELP}.")
    serve.add_argument("station", metavar="STATION", help="station file (.toml) or example name")
    serve.add_argument("--time-scale", type=TIME_SCALE, help=TIME_SCALE_HELP)
    serve.add_argument("--seed", type=SEED, help="the simulated rig's random seed")
    serve.add_argument("--json", action="store_true", help="print where they listen as JSON on stdout")
    serve.set_defaults(func=cmd_serve)
