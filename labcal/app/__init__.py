"""The application layer: one function per use case, taking a typed request, returning a typed result.

The command line (`labcal.commands`) and the lab server call these and nothing below them: a
command parses its options into a request, calls one function, and prints the result as text or
JSON. Each use case exists once here, so the two front ends cannot drift apart.

Reads are pure: listing runs, reading a run's log, the histories, verifying a certificate and
exporting a run to another folder change neither a run folder nor the lab database. The use
cases that write say so in their names: rebuilding a run folder, issuing, approving, running.
"""

# The statuses a run can be listed by. Here, not in `labcal.app.runs`, so that `labcal --help` (whose
# `runs --status` offers them) does not load that module and dataclasses with it.
STATUSES = ("running", "complete", "stopped", "interrupted", "failed")
