"""The run's events: what the sequencer reports, typed, and the bus that delivers them.

The sequencer does not call its audiences (the journal, the console, the lab database sync, a web
stream, a notifier); it publishes one event per thing that happened, and an `EventBus` hands it
to each subscriber. Delivery has two tiers, because the audiences are not equal:

- **durable** subscribers (the journal, `labcal.run.journaling`) get every event first, in the
  order they subscribed, and their exceptions propagate: a point that is not on disk is not
  measured, so the run stops (its tables stopped) rather than move on without it;
- every **other** subscriber gets it next; an exception it raises is caught, logged once per
  subscriber at WARNING, and never stops the run: a lab database server that is away, a
  notification refused or a closed browser tab must not cost a calibration its points (the journal
  has them, and the lab database is synced from the journal).

A subscriber may ask for some kinds only (``kinds=("prompt", "pause", "status")``). Events are
published on the run's thread; a subscriber that does slow I/O should hand the event to a
thread of its own. ``KeyboardInterrupt`` and the other non-``Exception`` errors (a second Ctrl-C
while a subscriber runs) always propagate: they are how a run is stopped.

Every event the journal keeps maps to exactly one row of its events table (`RunEvent.journal_entry`)
with the kind, message and data the journal had before events existed, so that `labcal log`, the
certificate's story and the lab database read the same story; a prompt's data adds its named
fields beside the positional ``args`` it always kept (`JournaledPrompt` reads either).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, field_validator

from labcal.store.journal import PointRecord, utc_now

log = logging.getLogger(__name__)

JournalEntry = tuple[str, str, dict[str, Any] | None]  # the events table's kind, message and data
RunStatus = Literal["running", "complete", "stopped", "interrupted", "failed"]


class RunEvent(BaseModel):
    """What every event says: which run, when on the rig's clock and when in UTC."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    run_id: int
    rig_time_s: float  # rig seconds since the run began (the journal's station_time)
    utc: str = Field(default_factory=utc_now)

    def journal_entry(self) -> JournalEntry | None:
        """The events-table row of this event (kind, message, data); None: not journaled as an event
        (a point has its own table; a Status between milestones is not kept)."""
        raise NotImplementedError


class PointMeasured(RunEvent):
    """A point measured (or failed to settle) and committed: the journal's record and its raw
    samples ride along for the journal (``record``, ``samples``, read-only). They are left out of
    ``model_dump``/``model_dump_json`` (a stream's clients get the figures above them), so an event
    read back from JSON has neither."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)

    kind: Literal["point"] = "point"
    seq: int
    replicate: int
    mount: int = Field(ge=1, le=4)  # the orientation's number in Soto Table 3 (`mount_number`)
    pitch_deg: float
    roll_deg: float
    volts: tuple[float, float, float]
    settle_s: float | None
    ok: bool  # settled; False: journaled as failed (the plan's on_failure policy applies)
    points_done: int  # points of the run in the journal, this one included (ok and failed)
    points_total: int
    record: PointRecord | None = Field(default=None, exclude=True, repr=False)
    samples: np.ndarray | None = Field(default=None, exclude=True, repr=False)  # a row per sample: vx vy vz T

    @field_validator("samples")
    @classmethod
    def _read_only(cls, samples: np.ndarray | None) -> np.ndarray | None:
        if samples is not None:
            samples.setflags(write=False)  # the event is frozen: so are the readings it carries
        return samples

    def journal_entry(self) -> JournalEntry | None:
        return None  # the points table (`Journal.record_point`)


class Prompt(RunEvent):
    """The operator is asked something; the tables are still until it is answered."""

    kind: Literal["prompt"] = "prompt"
    what: Literal["mount", "pause"]
    mount: int | None = Field(default=None, ge=1, le=4)  # the mount asked for (a "mount" prompt)
    step: int | None = None  # mount ``step`` of ``n_steps`` (a "mount" prompt)
    n_steps: int | None = None
    message: str  # what the operator is told, in plain words
    where: str = ""  # the mount asked for, as the operator is shown it (a "mount" prompt)
    note: str = ""  # why the mount is asked (again): a replicate's re-seat, a wrong mount to correct
    why: str = ""  # what paused the run (a "pause" prompt)
    may_be_moving: tuple[str, ...] = ()  # tables whose stop failed (a "pause" prompt)
    args: tuple[str, ...] = ()  # the same, positionally, as journals before the named fields kept them

    def journal_entry(self) -> JournalEntry:
        named = self.model_dump(mode="json", exclude={"run_id", "rig_time_s", "utc", "kind", "what", "args"})
        return "prompt", self.what, {"args": list(self.args), **named}


class JournaledPrompt(BaseModel):
    """A prompt read back from the journal (its events-table message and data): by its named fields,
    or, in a journal from before they were kept, by its positional ``args``: a mount's where, step,
    of how many and the note when asked again; a pause's why and the tables that may still move."""

    model_config = ConfigDict(frozen=True)

    what: str
    where: str = ""
    step: int | None = None
    n_steps: int | None = None
    note: str = ""
    why: str = ""
    args: tuple[str, ...] = ()  # as journaled, empty ones left out

    @classmethod
    def read(cls, what: str, data: dict[str, Any]) -> JournaledPrompt:
        """``what`` and ``data``: the events-table row's message and data (a pydantic ValidationError
        where they are not a prompt labcal journaled)."""
        args = tuple(str(a) for a in data.get("args") or () if str(a))
        if "where" in data or "why" in data:  # the named fields, kept since they were added
            return cls.model_validate({**data, "what": what, "args": args})
        positional: dict[str, Any] = {}
        if what == "mount" and len(args) >= 3:
            positional = dict(zip(("where", "step", "n_steps", "note"), args, strict=False))
        elif what == "pause" and args:
            positional = {"why": args[0]}
        return cls.model_validate({**positional, "what": what, "args": args})

    def text(self) -> str:
        """The prompt in words for people: what it asks."""
        if self.what == "mount" and self.step is not None:
            note = f" ({self.note})" if self.note else ""
            return f"mount {self.step} of {self.n_steps}: {self.where}{note}"
        if self.what == "pause" and self.why:
            return f"paused: {self.why}"
        return f"{self.what}: {', '.join(self.args)}" if self.args else self.what


STAYS_OPEN = "the prompt stays open"  # in the journal's line of an answer that does not close its prompt


class Answer(RunEvent):
    """A reply to a prompt: one that keeps it open ("n"), the one that closes it, or none (declined:
    the operator stopped the run there, or an unattended run had no answer left)."""

    kind: Literal["answer"] = "answer"
    what: Literal["mount", "pause"]  # the prompt answered
    reply: str  # as typed; "confirmed" for a mount, "declined" when none came
    meaning: str  # "not yet", "not one of the answers", "confirmed", "resume", "abort", or why declined
    outcome: Literal["open", "answered", "declined"]

    def journal_entry(self) -> JournalEntry:
        if self.outcome == "open":
            return "answer", f"{self.what}: {self.reply!r} ({self.meaning}; {STAYS_OPEN})", None
        if self.outcome == "declined":
            return "answer", f"{self.what}: declined", {"reason": self.meaning}
        return "answer", f"{self.what}: {self.reply}", None


class Fault(RunEvent):
    """A device that does not answer, a table fault, a wrong mount, a point that did not settle."""

    kind: Literal["fault"] = "fault"
    message: str
    policy: str | None = None  # a point that did not settle: the run's on_failure policy

    def journal_entry(self) -> JournalEntry:
        return "fault", self.message, None if self.policy is None else {"policy": self.policy}


class Paused(RunEvent):
    """The run is paused at a prompt (after Ctrl-C or a fault); ``may_be_moving``: tables whose
    stop failed."""

    kind: Literal["pause"] = "pause"
    why: str
    may_be_moving: tuple[str, ...] = ()

    def journal_entry(self) -> JournalEntry:
        return "pause", self.why, {"may_be_moving": list(self.may_be_moving)}


class Resumed(RunEvent):
    """The operator resumed after a pause."""

    kind: Literal["resume"] = "resume"
    why: str

    def journal_entry(self) -> JournalEntry:
        return "resume", self.why, None


class Stopped(RunEvent):
    """Both tables were told to stop (a fault, Ctrl-C, a signal); ``failed``: what a stop that did
    not reach a table said (then ``may_be_moving`` names the tables)."""

    kind: Literal["stop"] = "stop"
    cause: str
    failed: str | None = None
    may_be_moving: tuple[str, ...] = ()

    def journal_entry(self) -> JournalEntry:
        if self.failed is None:
            return "stop", "both tables stopped", {"cause": self.cause}
        return "stop", f"stop failed: {self.failed}", {"may_be_moving": list(self.may_be_moving),
                                                       "cause": self.cause}


class Discarded(RunEvent):
    """A window the tables did not vouch for or the settle test refused, journaled with its readings
    (nothing taken is lost): the point is measured again, or (``faulted``) the run pauses."""

    kind: Literal["discarded"] = "discarded"
    seq: int
    attempt: int
    reason: str
    faulted: bool
    volts: tuple[float, float, float]
    sd: tuple[float, float, float]
    samples: tuple[tuple[float | None, ...], ...]  # vx vy vz T per sample, None where NaN (no temperature)

    def journal_entry(self) -> JournalEntry:
        then = "the run pauses" if self.faulted else "measured again"
        return "discarded", f"point {self.seq}: readings discarded, {then}: {self.reason}", {
            "seq": self.seq, "attempt": self.attempt, "reason": self.reason, "volts": list(self.volts),
            "sd": list(self.sd), "samples": [list(row) for row in self.samples]}


class Note(RunEvent):
    """Everything else the run journals, under the journal's own kind (``name``): each move before
    it starts ("move"), a retry, a verified mount ("mount"), a segment's clock ("segment"), a
    device's warning ("link"), model settling's pool ("settle_pool")."""

    kind: Literal["note"] = "note"
    name: str
    message: str
    data: dict[str, Any] | None = None

    def journal_entry(self) -> JournalEntry:
        return self.name, self.message, self.data


class Status(RunEvent):
    """Where the run stands: published at the start, after every point, after each mount is
    confirmed, on resuming after a pause, and at the end (``at``). The live figures are the plan's
    estimates on the rig's clock (`labcal.run.estimate`): ``next_remount_in_s`` is the rig time
    until the next remount prompt (None: no remount left), ``eta_s`` the rest of the run.

    The journal keeps the milestones only (``at`` "mount", "resume", "end"): a status per point
    would add a row per point to the events table and fill `labcal log` and the certificate's story,
    and the figures between milestones follow from the points' rig times."""

    kind: Literal["status"] = "status"
    status: RunStatus
    reason: str | None = None
    at: Literal["start", "point", "mount", "thermal", "resume", "end"]  # thermal: waiting at the gate
    points_done: int
    points_total: int
    mount: int | None = Field(default=None, ge=1, le=4)  # the mount on the plate (None: none yet)
    next_remount_in_s: float | None = None
    eta_s: float | None = None  # None: no estimate given (a run started without one)

    def journal_entry(self) -> JournalEntry | None:
        if self.at in ("start", "point", "thermal"):  # the gate's wait is journaled as its own note
            return None
        figures = self.model_dump(include={"status", "reason", "at", "points_done", "points_total", "mount",
                                           "next_remount_in_s", "eta_s"})
        text = f"{self.status}: {self.points_done} of {self.points_total} points"
        return "status", text + (f" ({self.reason})" if self.reason else ""), figures


Event = Annotated[PointMeasured | Prompt | Answer | Fault | Paused | Resumed | Stopped | Discarded | Note
                  | Status, Field(discriminator="kind")]
EVENTS: TypeAdapter[Event] = TypeAdapter(Event)  # reads an event back from its JSON (a stream's client)
KINDS = frozenset(cls.model_fields["kind"].default for cls in (PointMeasured, Prompt, Answer, Fault, Paused,
                                                               Resumed, Stopped, Discarded, Note, Status))
SCHEMA_FILE = "schemas/run-events.schema.json"


def json_schema() -> dict[str, Any]:
    """The published JSON Schema (draft 2020-12) of a run's events as a subscriber's or a stream
    client's JSON carries them (`RunEvent.model_dump_json`: a point without the journal's record and
    samples), one kind each, told apart by ``kind``: `SCHEMA_FILE`, written by
    tools/schemas.py, so that a program that follows a run reads its events without labcal."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            **EVENTS.json_schema(mode="serialization"), "title": "labcal run event"}

Handler = Callable[[RunEvent], None]


@dataclass(eq=False)
class Subscription:
    """One subscriber: its handler, the kinds it asked for (None: all) and its tier."""

    handler: Handler
    kinds: frozenset[str] | None
    durable: bool
    failures: int = 0  # exceptions caught (a non-durable subscriber); the first one is logged

    def wants(self, event: RunEvent) -> bool:
        return self.kinds is None or getattr(event, "kind", None) in self.kinds


class EventBus:
    """Delivers each event to the durable subscribers, then to the others (see the module)."""

    def __init__(self) -> None:
        self._durable: list[Subscription] = []
        self._others: list[Subscription] = []

    def subscribe(self, handler: Handler, *, kinds: Iterable[str] | None = None,
                  durable: bool = False, first: bool = False) -> Subscription:
        """Call ``handler(event)`` for every event (of ``kinds``, if given). ``durable``: the handler
        must not miss an event, and its failure stops the run (the journal is the one; others, such
        as a notifier or a database sync, are not durable). ``first``: before the others of its tier
        (the run subscribes its journal so). An unknown kind is refused at once: a misspelt kind
        would otherwise be a subscriber that silently never hears anything."""
        wanted = None if kinds is None else frozenset(kinds)
        if wanted is not None and (unknown := wanted - KINDS):
            raise ValueError(f"unknown event kind(s) {sorted(unknown)}; the kinds are {sorted(KINDS)}")
        subscription = Subscription(handler, wanted, durable)
        tier = self._durable if durable else self._others
        tier.insert(0 if first else len(tier), subscription)
        return subscription

    def unsubscribe(self, subscription: Subscription) -> None:
        for tier in (self._durable, self._others):
            if subscription in tier:
                tier.remove(subscription)

    def publish(self, event: RunEvent,
                critical: Callable[[], AbstractContextManager[object]] = nullcontext) -> None:
        """Deliver ``event``: durable subscribers inside ``critical()`` (the run's: a stop waits until
        the journal has the event, never cutting its transaction in half), then the others outside
        it (a slow notifier never delays a stop)."""
        with critical():
            for subscription in self._durable:
                if subscription.wants(event):
                    subscription.handler(event)
        for subscription in tuple(self._others):
            if not subscription.wants(event):
                continue
            try:
                subscription.handler(event)
            except Exception:
                subscription.failures += 1
                if subscription.failures == 1:
                    log.warning("event subscriber %r failed on a %s event; the run goes on, and its later "
                                "failures are not logged again", subscription.handler,
                                getattr(event, "kind", "?"), exc_info=True)


def mount_number(y_deg: float, u_deg: float) -> int:
    """The mount's number in Soto Table 3: 1 (y 0°, u 0°), 2 (180°, 0°), 3 (0°, 180°), 4 (180°, 180°)."""
    return 1 + (y_deg % 360 == 180) + 2 * (u_deg % 360 == 180)
