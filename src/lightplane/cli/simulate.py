"""`lightplane simulate` (not implemented yet: its issue is open)."""

from __future__ import annotations

from ._common import app, fail


@app.command("simulate", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def simulate() -> None:
    """Not implemented yet."""
    fail("'simulate' is not implemented yet")
