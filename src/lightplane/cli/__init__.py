"""The ``lightplane`` command: one program, one module per subcommand.

Each subcommand is a thin shell over one library function: parse, call, print
a summary with units, write files atomically.  Bad input (``LightplaneError``,
a missing file...) gives one line on stderr and exit status 2.
"""

from __future__ import annotations

from lightplane.cli._common import app

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
    app()


__all__ = ["app", "main"]
