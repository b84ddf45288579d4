"""The journal as the run's first, durable event subscriber.

Each point is one transaction with its raw samples, committed before the next move; every other
event the journal keeps is one row of its events table, with the kind, message and data it has
always had (`labcal.run.events.RunEvent.journal_entry`). The row's UTC time is the event's, so that
the journal, the lab database and a live view agree on when something happened.
"""

from __future__ import annotations

from labcal.run.events import EventBus, PointMeasured, RunEvent, Subscription
from labcal.store.journal import Journal


class JournalSubscriber:
    """Writes a run's events into its journal (subscribe it ``durable=True``, before any other)."""

    def __init__(self, journal: Journal):
        self.journal = journal

    def __call__(self, event: RunEvent) -> None:
        if isinstance(event, PointMeasured):
            if event.record is None:  # read back from JSON: the readings are not in it
                raise ValueError(f"point {event.seq} of run {event.run_id} has no record to journal")
            self.journal.record_point(event.run_id, event.record, event.samples, utc=event.utc)
            return
        entry = event.journal_entry()
        if entry is not None:
            kind, message, data = entry
            self.journal.event(event.run_id, kind, message, data, event.rig_time_s, utc=event.utc)


def subscribe_journal(bus: EventBus, journal: Journal) -> Subscription:
    """The journal, subscribed first and durably: it has every event before anyone else sees it,
    another durable subscriber included."""
    return bus.subscribe(JournalSubscriber(journal), durable=True, first=True)
