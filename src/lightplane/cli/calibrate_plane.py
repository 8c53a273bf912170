"""`lightplane calibrate-plane` (not implemented yet: its issue is open)."""

from __future__ import annotations

from ._common import app, fail


@app.command("calibrate-plane", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def calibrate_plane() -> None:
    """Not implemented yet."""
    fail("'calibrate-plane' is not implemented yet")
