"""One module per command group; its `register(subparsers)` adds its parsers.

Every command is named here, with the module that adds it and its one-line help, so that `labcal
--help` lists them all without importing any command's module or building its parser (that was most
of its time); `labcal COMMAND …` builds only that command's.
"""

COMMANDS = {  # name: (module, one-line help), in the order `labcal --help` lists them
    "run": ("run", "run a calibration (on the simulated rig with --sim, or on a --station)"),
    "resume": ("run", "continue an interrupted run where it stopped"),
    "fit": ("fit", "fit calibration coefficients to a readings CSV"),
    "simulate": ("simulate", "write readings straight from a plan and a truth"),
    "plan": ("plan", "list, show and design calibration plans"),
    "attitude": ("attitude", "pitch and roll with uncertainty from voltages"),
    "report": ("report", "certificate and report of a finished run; stores it in the history"),
    "history": ("history", "an instrument's coefficients over time, drift flagged"),
    "runs": ("runs", "list the lab's runs (lab number, serial, plan, status, start, points)"),
    "log": ("runs", "a run's journaled events: prompts, answers, retries, faults, pauses"),
    "device": ("device", "the calibration device's own history"),
    "station": ("station", "example stations; check that a station's devices answer"),
    "sim": ("sim", "protocol emulators of a station's devices"),
    "export": ("export", "rebuild a run folder from the journal, or copy it elsewhere (--out)"),
    "config": ("config", "the lab-wide configuration file: where it is and what it says"),
    "certificate": ("certificate", "approve (sign) a certificate, verify a signature, make keys"),
    "db": ("db", "the lab database's schema: its revision, and upgrading it"),
    "sync": ("sync", "send this station's journal to the lab's PostgreSQL database now"),
    "serve": ("serve", "the lab server: every station's runs live, the API, approvals"),
    "user": ("user", "the lab server's users: add, list, disable"),
    "instrument": ("instrument", "the lab's instrument register: add, list, show, edit"),
    "due": ("instrument", "instruments overdue or falling due; --notify sends the recall"),
    "standard": ("standard", "the lab's reference standards; an approver's override for an overdue one"),
}


def summary(name: str) -> str:
    """A command's one-line help, as `labcal --help` lists it."""
    return COMMANDS[name][1]
