"""Shared plumbing of the subcommands: the Typer app, error handling, console."""

from __future__ import annotations

import functools
import sys
from typing import Callable, TypeVar

import typer
from rich.console import Console

from ..errors import LightplaneError

app = typer.Typer(
    name="lightplane",
    help="Line-structured-light calibration (single circular target, Wang & Li 2022) and 3D measurement.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

console = Console(highlight=False, soft_wrap=True)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)  # one warning, one line

F = TypeVar("F", bound=Callable)


def fail(message: str, code: int = 2) -> None:
    """One clear line on stderr, then exit with ``code`` (2: bad input)."""
    print(f"lightplane: error: {message}", file=sys.stderr)
    raise typer.Exit(code)


def quiet_native_logs() -> None:
    """Keep OpenCV's log lines and the image decoders' (libpng, libjpeg, libtiff) own
    complaints off stderr, so that a bad image gives only our one line; the reason of
    each skipped image is in the summary and the result file.  Once per process."""
    global _QUIETED
    if not _QUIETED:
        from ..io import quiet_opencv

        quiet_opencv()
        _QUIETED = True


_QUIETED = False


def handles_errors(fn: F) -> F:
    """Turn LightplaneError / missing files into one stderr line and exit 2.

    Also quiets OpenCV's own logging first (:func:`quiet_native_logs`)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            quiet_native_logs()
            return fn(*args, **kwargs)
        except LightplaneError as e:
            fail(str(e))
        except FileNotFoundError as e:
            fail(f"{e.filename}: no such file")
        except PermissionError as e:
            fail(f"{e.filename}: permission denied")
        except KeyboardInterrupt:
            fail("interrupted", code=130)

    return wrapper  # type: ignore[return-value]


def parse_board(text: str) -> tuple[int, int]:
    """'COLSxROWS' (inner corners) -> (cols, rows)."""
    try:
        cols, rows = (int(t) for t in text.lower().split("x"))
    except ValueError:
        raise LightplaneError(f"--board must look like COLSxROWS (inner corners), e.g. 9x6; got {text!r}") from None
    if cols < 2 or rows < 2:
        raise LightplaneError(f"--board needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


# The board options, the same in every command that takes a board (calibrate-camera,
# calibrate-plane-board, evaluate): parsed by target_from_options.
BOARD_HELP = ("Board, KIND:COLSxROWS: chessboard (default kind; inner corners, e.g. 9x6), circles (symmetric grid, "
              "dots), acircles (asymmetric grid, OpenCV's convention) or charuco (squares, with --marker, --dictionary).")
board_option = typer.Option(None, "--board", help=BOARD_HELP)
square_option = typer.Option(None, "--square", help="Square size in mm (circle grids: the centre pitch).")
marker_option = typer.Option(None, "--marker", help="ChArUco marker size in mm.")
dictionary_option = typer.Option(None, "--dictionary", help="ChArUco ArUco dictionary, e.g. DICT_5X5_100 "
                                 "(default DICT_4X4_50).")
dot_option = typer.Option(None, "--dot", help="Circle grids: dot diameter in mm (default: measured in the images).")
target_option = typer.Option(None, "--target", help="Target file (JSON) naming the board once, instead of --board/--square.")


def target_from_options(board, square, marker=None, dictionary=None, dot=None, target_file=None):
    """The :class:`lightplane.targets.Target` named on the command line."""
    from ..targets import parse_target

    return parse_target(board, square, marker_mm=marker, dictionary=dictionary, dot_mm=dot, target_file=target_file)
