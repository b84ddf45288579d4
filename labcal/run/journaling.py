"""The journal as the run's first, durable event subscriber.

Each point is one transaction with its raw samples, committed before the next move; every other
event the journal keeps is one row of its events table, with the kind, message and data it has
always had (`labcal.run.events.RunEvent.journal_entry`). The row's UTC time is the event's, so that
the journal, the lab database and a live view agree on when something happened.
"""

from __future__ import annotations

from labcal.run.events import EventBus, PointMeasured, RunEvent, Subscription
from labcal.run.journal import Journal


class JournalSubscriber:
    """Writes a run's events into its journal (subscribe it ``durable=True``, before any other)."""

    def __init__(self, journal: Journal):
        self.journal = journal

    def __call__(self, event: RunEvent) -> None:
        if isinstance(event, PointMeasured):
            self.journal.record_point(event.run_id, event.record, event.samples, utc=event.utc)
            return
        entry = event.journal_entry()
        if entry is not None:
            kind, message, data = entry
            self.journal.event(event.run_id, kind, message, data, event.rig_time_s, utc=event.utc)


def subscribe_journal(bus: EventBus, journal: Journal) -> Subscription:
    """The journal, subscribed first and durably: it has every event before anyone else sees it.
    A bus that already has a durable subscriber is refused (it would hear of points not yet on disk)."""
    if bus.durable:
        raise ValueError("the journal must be the run's first durable subscriber; subscribe the others "
                         "after the run has started, or not durably")
    return bus.subscribe(JournalSubscriber(journal), durable=True)
