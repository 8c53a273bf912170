"""Shared plumbing of the subcommands: the Typer app, error handling, console."""

from __future__ import annotations

import contextlib
import functools
import inspect
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Literal, Optional, TypeVar

import typer
from rich.console import Console
from typer.core import TyperGroup

try:  # typer >= 0.20 carries its own copy of click
    from typer._click import exceptions as _click_errors
except ImportError:  # pragma: no cover
    from click import exceptions as _click_errors  # type: ignore[no-redef]  # the same module, older typer

from lightplane.core.errors import LightplaneError
from lightplane.camera.model import ALLOWED_CAMERA_KEY, Camera, camera_record
from lightplane.camera.targets import parse_target
from lightplane.core.io import DEFAULT_MAX_PIXELS, MAX_PIXELS_ENV, check_output, quiet_opencv
from lightplane.measure.sensor import Sensor
from lightplane.motion.model import Turntable
from lightplane.plane.model import LightPlane, check_camera

class _OneLineErrors(TyperGroup):
    """The command group, with click's usage errors (a bad choice, a value out of range, a
    missing option...) as one line on stderr and exit status 2, like every other bad input."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except _click_errors.NoArgsIsHelpError as e:
            e.show()
            sys.exit(e.exit_code)
        except _click_errors.ClickException as e:
            print(f"lightplane: error: {one_line(e.format_message())}", file=sys.stderr)
            sys.exit(e.exit_code)
        except typer.Abort:
            print("lightplane: error: aborted", file=sys.stderr)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)


def one_line(text: str) -> str:
    """``text`` on one line (click's messages may span several)."""
    return " ".join(str(text).replace("Value error, ", "").split())


# Choices are declared as ``Literal[...]`` annotations (typer turns them into click choices:
# a bad value is a usage error, one line, exit 2); ranges as ``min=``/``max=``.
Channel = Literal["red", "green", "blue", "gray"]

app = typer.Typer(
    cls=_OneLineErrors,
    name="lightplane",
    help="Line-structured-light calibration (single circular target, Wang & Li 2022) and 3D measurement.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)



@app.callback()
def _global_options(
    max_pixels: Optional[int] = typer.Option(
        None, "--max-pixels", min=1, metavar="PIXELS",
        help=f"Largest image or video frame read (width x height, pixels), checked in the file's header before "
             f"decoding; default {DEFAULT_MAX_PIXELS:,} (or the {MAX_PIXELS_ENV} environment variable)."),
) -> None:
    """Line-structured-light calibration (single circular target, Wang & Li 2022) and 3D measurement."""
    if max_pixels is not None:  # the environment carries it to worker processes too
        os.environ[MAX_PIXELS_ENV] = str(max_pixels)


console = Console(highlight=False, soft_wrap=True)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)  # one warning, one line

F = TypeVar("F", bound=Callable)


def fail(message: str, code: int = 2) -> None:
    """One clear line on stderr, then exit with ``code`` (2: bad input)."""
    print(f"lightplane: error: {message}", file=sys.stderr)
    raise typer.Exit(code)


@contextlib.contextmanager
def progress_bar(label: str, total: int | None = None, *, remaining: bool = False) -> Iterator[Callable[..., None]]:
    """A transient progress bar on the console (label, bar, done/total, elapsed time).

    Yields ``update(completed=None, *, total=None, advance=None, label=None)``: set the count
    done (or add ``advance`` to it), change the total or the label.  ``remaining``: also show
    the estimated time left.
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()]
    if remaining:
        columns.append(TimeRemainingColumn())
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task(label, total=total)

        def update(completed: float | None = None, *, total: float | None = None, advance: float | None = None,
                   label: str | None = None) -> None:
            bar.update(task, completed=completed, total=total, advance=advance, description=label)

        yield update


def quiet_native_logs() -> None:
    """Keep OpenCV's log lines and the image decoders' (libpng, libjpeg, libtiff) own
    complaints off stderr, so that a bad image gives only our one line; the reason of
    each skipped image is in the summary and the result file.  Once per process."""
    global _QUIETED
    if not _QUIETED:
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
    """The :class:`lightplane.camera.targets.Target` named on the command line."""
    return parse_target(board, square, marker_mm=marker, dictionary=dictionary, dot_mm=dot, target_file=target_file)


_KW = inspect.Parameter.POSITIONAL_OR_KEYWORD
_TARGET_PARAMS = (
    inspect.Parameter("board", _KW, default=board_option, annotation=Optional[str]),
    inspect.Parameter("square", _KW, default=square_option, annotation=Optional[float]),
    inspect.Parameter("marker", _KW, default=marker_option, annotation=Optional[float]),
    inspect.Parameter("dictionary", _KW, default=dictionary_option, annotation=Optional[str]),
    inspect.Parameter("dot", _KW, default=dot_option, annotation=Optional[float]),
    inspect.Parameter("target_file", _KW, default=target_option, annotation=Optional[Path]),
)


#: The default of a command's ``target`` parameter, replaced by the board options (:func:`takes_target`).
BOARD_OPTIONS: Any = object()


def takes_target(fn: F) -> F:
    """Give a command the board options (``--board/--square/--marker/--dictionary/--dot`` or
    ``--target``) in place of its ``target`` parameter, which receives the
    :class:`~lightplane.camera.targets.Target` they name.  Put it below ``handles_errors``, so
    that a bad board is one line and exit 2 like any other bad input."""
    sig = inspect.signature(fn)
    names = list(sig.parameters)
    if "target" not in names:
        raise TypeError(f"{fn.__name__} has no 'target' parameter")
    at = names.index("target")
    params = list(sig.parameters.values())
    params[at:at + 1] = _TARGET_PARAMS

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        given = [kwargs.pop(p.name, None) for p in _TARGET_PARAMS]
        kwargs["target"] = target_from_options(*given)
        return fn(*args, **kwargs)

    wrapper.__signature__ = sig.replace(parameters=params)  # type: ignore[attr-defined]
    return wrapper  # type: ignore[return-value]


# Several lasers, the same option in every plane-calibration command (lightplane.stripe.lasers).
LASER_HELP = ("One laser of several, NAME=SELECTOR (repeat per laser; one plane file each): its stripe told apart by "
              "a colour (red, green, blue, gray), a region x0,y0,x1,y1 (px, after --rotate), frames:PATTERN (its "
              "image files) or cycle:K (the K-th laser frame of each pose), parts joined by +. E.g. --laser left=red "
              "--laser right=green. Files: -o plane.json gives plane_NAME.json, or use {laser} in -o.")
laser_option = typer.Option(None, "--laser", help=LASER_HELP)


# ------------------------------------------------------------------ outputs
def output_file(path: str | os.PathLike, force: bool, *, inputs: Iterable[Any] = (), option: str = "-o",
                suffixes: tuple[str, ...] = ()) -> Path:
    """Check a file a command will write, before any work; one line on bad input.

    Refused: an existing folder (with or without ``--force``), a file named among ``inputs`` (the
    command's input files: the same path, or the same file through a link), a suffix not among
    ``suffixes`` when given; then :func:`lightplane.core.io.check_output` (exists without
    ``--force``, no such or unwritable folder)."""
    p = Path(path)
    if p.is_dir():
        raise LightplaneError(f"{option} {p}: is a folder; give a file name")
    for item in inputs:
        if item is not None and _same_file(p, Path(item)):
            raise LightplaneError(f"{option} {p}: is also an input of this command; give another output file")
    if suffixes and p.suffix.lower() not in suffixes:
        raise LightplaneError(f"{option} {p}: the file name must end in {' or '.join(suffixes)}")
    return check_output(p, force)


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except OSError:
        return False


# ------------------------------------------------------ plane and camera together
ALLOW_OTHER_CAMERA_HELP = ("Use a plane, sensor or turntable file calibrated with another camera than the one given "
                           "(refused otherwise); the output's provenance records it.")
allow_other_camera_option = typer.Option(False, "--allow-other-camera", help=ALLOW_OTHER_CAMERA_HELP)


@dataclass
class CameraFiles:
    """The camera of a command and the calibration files read against it: every plane and turntable
    is checked to belong to ``camera`` (:func:`lightplane.plane.model.check_camera`; refused in one
    line naming both files unless ``allow_other``).  ``notes``: what the check let through (older
    files that record no camera, another camera allowed), for the console and the provenance."""

    camera: Camera
    camera_file: str
    allow_other: bool = False
    notes: list[str] = field(default_factory=list)

    @classmethod
    def load(cls, camera_file: str | os.PathLike, allow_other: bool = False) -> "CameraFiles":
        return cls(Camera.load(camera_file), str(camera_file), allow_other)

    def _note(self, note: str | None) -> None:
        if note is not None and note not in self.notes:
            self.notes.append(note)

    def plane(self, path: str | os.PathLike, source: str | None = None) -> LightPlane:
        """The plane file ``path``, checked against the camera."""
        pl = LightPlane.load(path)
        self.check_plane(pl, source or str(path))
        return pl

    def check_plane(self, plane: LightPlane, source: str) -> None:
        self._note(check_camera(plane, self.camera, plane_file=source, camera_file=self.camera_file,
                                allow_other=self.allow_other))

    def turntable(self, path: str | os.PathLike) -> Turntable:
        """The turntable file ``path``, checked against the camera."""
        tt = Turntable.load(path)
        self.check_turntable(tt, str(path))
        return tt

    def check_turntable(self, table: Turntable, source: str) -> None:
        self._note(table.check_camera(self.camera, source, camera_file=self.camera_file, allow_other=self.allow_other))

    def allowed(self) -> dict:
        """What a part recorded with it in a sensor file carries when another camera was allowed."""
        return {ALLOWED_CAMERA_KEY: camera_record(self.camera)} if self.allow_other else {}

    def record(self) -> dict:
        """For the output's provenance options: the flag and the notes."""
        return {"allow_other_camera": self.allow_other, "camera_check": list(self.notes)}

    def comments(self) -> tuple[str, ...]:
        """For a point cloud's comment lines."""
        head = ("camera check: --allow-other-camera given",) if self.allow_other else ()
        return head + tuple(f"camera check: {n}" for n in self.notes)

    def warn(self) -> None:
        """Each note as one warning line on stderr."""
        for n in self.notes:
            err_console.print(f"warning: {n}")


def load_sensor(path: str | os.PathLike, allow_other: bool = False) -> tuple[Sensor, CameraFiles]:
    """A sensor file with its planes checked against its own camera (its turntable is checked on reading)."""
    sens = Sensor.load(path)
    cf = CameraFiles(sens.camera, f"{path} (its camera)", allow_other)
    for name, pl in sens.planes.items():
        cf.check_plane(pl, f"{path}: plane {name!r}")
    if sens.turntable is not None:
        cf.check_turntable(sens.turntable, f"{path}: turntable")
    return sens, cf
