"""`lightplane measure` (not implemented yet: its issue is open)."""

from __future__ import annotations

from ._common import app, fail


@app.command("measure", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def measure() -> None:
    """Not implemented yet."""
    fail("'measure' is not implemented yet")
