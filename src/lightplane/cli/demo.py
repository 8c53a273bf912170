"""`lightplane demo` (not implemented yet: its issue is open)."""

from __future__ import annotations

from ._common import app, fail


@app.command("demo", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def demo() -> None:
    """Not implemented yet."""
    fail("'demo' is not implemented yet")
