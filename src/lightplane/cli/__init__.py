"""The ``lightplane`` command: one program, one module per subcommand.

Each subcommand is a thin shell over one library function: parse, call, print
a summary with units, write files atomically.  Bad input (``LightplaneError``,
a missing file...) gives one line on stderr and exit status 2.
"""

from __future__ import annotations

from lightplane.cli._common import app
from lightplane.core.threads import blas_limited, ensure_configured

# Importing the modules registers their subcommands on ``app``.
from lightplane.cli import (  # noqa: E402,F401
    calibrate_camera,
    calibrate_plane,
    calibrate_plane_board,
    demo,
    evaluate,
    measure,
    measure_batch,
    refine_turntable,
    render,
    report,
    simulate,
    turntable,
)


def main() -> None:  # console-script entry point
    """The command line owns its process: lightplane's thread settings for all of it (core.threads)."""
    ensure_configured()
    with blas_limited():
        app()


__all__ = ["app", "main"]
