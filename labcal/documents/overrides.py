"""Every decision to go on regardless that a run was measured under, read from what the run journaled:
its metadata (the pre-run checklist, the reference standards' overrides) and its events (a fault the
operator resumed after). The approver signs what the run was measured under, so the certificate and
its report state each of these, and the lab's pages show them, all from this one reading:

- ``warm-up``: the warm-up check was not met and the operator said to go on;
- ``checklist item``: another unmet item of the pre-run checklist the operator went on regardless of;
- ``reference standard``: an overdue standard used under an approver's signed override, with its reason;
- ``fault accepted``: the run paused on a device fault and the operator resumed it.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

from labcal.config.dates import written_date
from labcal.config.run_metadata import Checklist, RunMetadata, StandardOverride

if TYPE_CHECKING:
    from labcal.store.journal import EventRow

FAULT_PAUSE = "fault: "  # how the sequencer's pause on a device fault begins its reason
OPERATOR_RESUMED = "operator resumed"  # the resume event of an answered pause (not `labcal resume`'s)


def checklist_overrides(checklist: Checklist | None) -> list[str]:
    """The pre-run checklist items a run went on regardless of (run.json's ``checklist``: unmet, and
    the operator said to go on), each as "item: what was found". The approver signs what the run was
    measured under, so the certificate states them; nothing when the run met its checklist."""
    return [] if checklist is None else [f"{i.item}: {i.message}" for i in checklist.overridden()]


@dataclass(frozen=True)
class Override:
    kind: str  # "warm-up", "checklist item", "reference standard", "fault accepted"
    what: str  # what was not as it should be
    by: str | None  # who decided (the operator, or the approver and their role)
    reason: str | None  # why, where one was given (an approver's override always says)
    utc: str | None  # when it was decided

    def to_json(self) -> dict:
        return asdict(self)

    def sentence(self) -> str:
        """One sentence, as the certificate's statements say it."""
        who = f" by {self.by}" if self.by else ""
        why = f": {self.reason.rstrip('.')}" if self.reason else ""
        return f"Override ({self.kind}){who}: {self.what.rstrip('.')}" + (f"; reason{why}" if why else "") \
            + "."


def _checklist(meta: RunMetadata) -> list[Override]:
    operator = meta.operator or "the operator"
    started = meta.started_utc
    found = []
    for line in checklist_overrides(meta.checklist):
        item, _, message = line.partition(": ")
        found.append(Override("warm-up" if item == "warm-up" else "checklist item", f"{item}: {message}",
                              operator, "the operator said to go on at the pre-run checklist", started))
    return found


STANDARD_OVERRIDE_EVENT = "standard_override"  # journaled where a resumed run goes on under one


def resumed_overrides(events: Iterable[EventRow]) -> list[StandardOverride]:
    """The approvers' overrides a run resumed under, as its ``standard_override`` events journal them."""
    return [StandardOverride.model_validate(e.data) for e in events if e.kind == STANDARD_OVERRIDE_EVENT]


def _standards(meta: RunMetadata, events: Iterable[EventRow]) -> list[Override]:
    """The overrides a run started under (its metadata) and those it resumed under (its events), once each."""
    found, seen = [], set()
    for held in [*(meta.standard_overrides or []), *resumed_overrides(events)]:
        if (held.serial, held.recorded_utc) in seen:
            continue
        seen.add((held.serial, held.recorded_utc))
        found.append(Override(
            "reference standard",
            f"reference standard {held.serial} was overdue (due {written_date(held.due_on)}) and used "
            f"under an override valid until {written_date(held.valid_until)}",
            f"{held.approver} ({held.role})", held.reason, held.recorded_utc))
    return found


def _faults(events: Iterable[EventRow], operator: str | None) -> list[Override]:
    """A pause on a device fault that the operator answered by resuming: the fault accepted."""
    found, paused = [], None
    for e in events:
        if e.kind == "pause":
            paused = e.message if e.message.startswith(FAULT_PAUSE) else None
        elif e.kind == "resume" and paused is not None:
            if e.message.startswith(OPERATOR_RESUMED):
                found.append(Override("fault accepted", f"the run paused on {paused} and was resumed",
                                      operator or "the operator", None, e.utc))
            paused = None
    return found


def run_overrides(meta: RunMetadata, events: Iterable[EventRow] = ()) -> list[Override]:
    """Every override of a run (see the module), checklist first, then standards, then faults in order."""
    events = list(events)
    return [*_checklist(meta), *_standards(meta, events), *_faults(events, meta.operator)]
