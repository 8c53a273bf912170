"""`lightplane render` (not implemented yet: its issue is open)."""

from __future__ import annotations

from ._common import app, fail


@app.command("render", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def render() -> None:
    """Not implemented yet."""
    fail("'render' is not implemented yet")
