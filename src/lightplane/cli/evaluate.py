"""`lightplane evaluate` (not implemented yet: its issue is open)."""

from __future__ import annotations

from ._common import app, fail


@app.command("evaluate", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def evaluate() -> None:
    """Not implemented yet."""
    fail("'evaluate' is not implemented yet")
