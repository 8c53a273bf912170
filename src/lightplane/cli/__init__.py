"""The ``lightplane`` command: one program, one module per subcommand.

Each subcommand is a thin shell over one library function: parse, call, print
a summary with units, write files atomically.  Bad input (``LightplaneError``,
a missing file...) gives one line on stderr and exit status 2.
"""

from __future__ import annotations

import signal
import sys

from lightplane.cli._common import app
from lightplane.core import jit
from lightplane.core.threads import blas_limited, ensure_configured

# Importing the modules registers their subcommands on ``app``.
from lightplane.cli import (  # noqa: E402,F401
    calibrate_camera,
    calibrate_plane,
    calibrate_plane_board,
    demo,
    evaluate,
    live,
    measure,
    measure_batch,
    plan,
    range_image,
    refine_turntable,
    render,
    report,
    simulate,
    turntable,
)


def _exit_on_sigterm(signum, frame) -> None:
    raise SystemExit(128 + signum)


def _compile_notice() -> None:
    print(jit.compile_notice(), file=sys.stderr, flush=True)


def main() -> None:  # console-script entry point
    """The command line owns its process: lightplane's thread settings for all of it (core.threads);
    SIGTERM ends it as an exit (temporary files are removed on the way out); the first kernel
    compilation is announced on stderr, in one line (core.jit)."""
    ensure_configured()
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    jit.set_compile_listener(_compile_notice)
    try:
        with blas_limited():
            app()
    finally:
        jit.record_compile_seconds()


__all__ = ["app", "main"]
