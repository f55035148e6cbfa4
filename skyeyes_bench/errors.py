"""Errors a user can fix. The CLI prints them as one line and exits 2 (no traceback)."""

from __future__ import annotations

from typing import Any


class UserError(Exception):
    """Bad input: a file, a field, a value. The message says what, where, and what was expected."""

    exit_code = 2


class ValidationError(UserError):
    """Several problems found at once (a dataset, a submission). `problems` keeps them all."""

    def __init__(self, what: str, problems: list[str]):
        self.what = what
        self.problems = list(problems)
        n = len(self.problems)
        if n == 1:  # one problem: one line, naming the file and field itself
            super().__init__(self.problems[0])
            return
        head = f"{what}: {n} problem{'s' if n != 1 else ''}"
        shown = self.problems[:20]
        more = f"\n  ... and {n - len(shown)} more" if n > len(shown) else ""
        super().__init__(head + "".join(f"\n  - {p}" for p in shown) + more)


def one_line(e: UserError) -> str:
    """A user error as one line (for a report that lists several): a validation's first problem
    and how many more there are."""
    if isinstance(e, ValidationError) and len(e.problems) > 1:
        return f"{e.problems[0]} (and {len(e.problems) - 1} more problem(s) of {e.what})"
    text = str(e)
    return text.splitlines()[0] if text else type(e).__name__


def single_line(msg: str) -> str:
    """Any message (an OSError, OpenImageIO's errors, which span several lines) as one line: its
    non-blank lines joined by '; '. User errors are one line."""
    return "; ".join(part.strip() for part in str(msg).splitlines() if part.strip())


def short(value: Any, limit: int = 80) -> str:
    """repr of `value` (controls escaped: a message stays one line), cut to `limit` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."
