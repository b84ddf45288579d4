"""The one exception type a user sees: a message that says what is wrong and what to do.

Below the front ends, a message that asks the caller for a value names it by its field, not by a
command-line option: ``LabcalError("the run does not record the serial; give {0}", "serial")``.
Each front end spells the field its own way (`Spelling`): the command line as ``--serial``, the
Python API as ``serial=``, the lab server's pages and JSON as ``serial``. So one rule, written
once where it is checked, reads right wherever it is raised, and a caller can read ``options``
to know which value was wrong without parsing a sentence.
"""

from __future__ import annotations

from typing import Literal

Spelling = Literal["cli", "python", "web"]


def spell(field: str, spelling: Spelling) -> str:
    """A request field as a front end's user types it: ``in_use_samples`` → ``--in-use-samples``,
    ``in_use_samples=`` or ``in_use_samples``."""
    if spelling == "cli":
        return "--" + field.replace("_", "-")
    return field + "=" if spelling == "python" else field


class LabcalError(Exception):
    """A user-facing error: the CLI prints its message on one line and exits with code 2.

    ``options`` are the request fields the message names, as ``{0}``, ``{1}`` … in ``message``;
    ``spelling`` is set by the front end that shows it (the command line's by default)."""

    def __init__(self, message: str, *options: str) -> None:
        super().__init__(message, *options)
        self.message = message
        self.options = options
        self.spelling: Spelling = "cli"

    def __str__(self) -> str:
        text = self.message  # {0}, {1} … replaced as they stand: a path with braces in it stays as it is
        for i, field in enumerate(self.options):
            text = text.replace(f"{{{i}}}", spell(field, self.spelling))
        return text

    def spelled(self, spelling: Spelling) -> LabcalError:
        """This error, its fields spelled for another front end (for ``raise exc.spelled(...)``)."""
        self.spelling = spelling
        return self
