"""Errors a user can fix. The CLI prints them as one line and exits 2 (no traceback)."""

from __future__ import annotations


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
