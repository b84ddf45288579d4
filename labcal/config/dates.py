"""Dates as people write them on a certificate: "27 November 2026", not ISO 8601's 2026-11-27, which a
reader may take for another order. The month is named in English whatever the computer's locale (the
certificate's language), so the same run gives the same document everywhere. The machine-read
documents (the JSON certificate, the DCC) keep ISO 8601, as their schemas require.
"""

from __future__ import annotations

from datetime import UTC, date, datetime

MONTHS = ("January", "February", "March", "April", "May", "June", "July", "August", "September",
          "October", "November", "December")


def written_date(day: date | datetime) -> str:
    """"27 November 2026" (a datetime's own calendar day)."""
    return f"{day.day} {MONTHS[day.month - 1]} {day.year}"


def written_time_utc(moment: datetime) -> str:
    """"27 November 2026, 21:12 UTC": the moment in UTC, to the minute (a naive one is taken as UTC)."""
    utc = moment.replace(tzinfo=UTC) if moment.tzinfo is None else moment.astimezone(UTC)
    return f"{written_date(utc)}, {utc:%H:%M} UTC"
