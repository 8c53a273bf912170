"""`lightplane calibrate-plane-board` (not implemented yet: its issue is open)."""

from __future__ import annotations

from ._common import app, fail


@app.command("calibrate-plane-board", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def calibrate_plane_board() -> None:
    """Not implemented yet."""
    fail("'calibrate-plane-board' is not implemented yet")
