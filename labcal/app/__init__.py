"""The application layer: one function per use case, taking a typed request, returning a typed result.

The command line (`labcal.commands`) and the lab server call these and nothing below them: a
command parses its options into a request, calls one function, and prints the result as text or
JSON. Each use case exists once here, so the two front ends cannot drift apart.

The lab server's use cases live here too: `labdatabase` (opening the lab database), `lab` (the
lab's overview, a run's detail and page, the next batch of a run's stream, the residual plot),
`users` (add, list, disable; a password or an API token to a user) and `server_approval` (a
certificate approved for the signed-in approver with the lab's key).

Reads are pure: listing runs, reading a run's log, the histories, verifying a certificate and
exporting a run to another folder change neither a run folder nor the lab database. The use
cases that write say so in their names: rebuilding a run folder, issuing, approving, running.
"""

# The statuses a run can be listed by. Here, not in `labcal.app.runs`, so that `labcal --help` (whose
# `runs --status` offers them) does not load that module and dataclasses with it.
STATUSES = ("running", "complete", "stopped", "interrupted", "failed")
