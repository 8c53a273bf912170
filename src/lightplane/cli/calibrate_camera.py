"""`lightplane calibrate-camera` (not implemented yet: its issue is open)."""

from __future__ import annotations

from ._common import app, fail


@app.command("calibrate-camera", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def calibrate_camera() -> None:
    """Not implemented yet."""
    fail("'calibrate-camera' is not implemented yet")
