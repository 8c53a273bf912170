"""``lightplane calibrate-plane-board``: Zhou's planar-target light-plane calibration (the baseline)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import numpy as np
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from ..errors import LightplaneError
from ..io import check_output, expand_inputs, provenance, read_image
from ._common import app, console, handles_errors, parse_board


def read_images(items: List[str], what: str, rotate: int) -> tuple[list[Path], list[np.ndarray]]:
    """Expand and read images; LightplaneError naming ``what`` when none match."""
    files = expand_inputs(items)
    if not files:
        raise LightplaneError(f"no {what} given (no files matched)")
    for f in files:
        if not f.is_file():
            raise LightplaneError(f"{f}: no such file")
    return files, [read_image(f, rotate_deg=rotate) for f in files]


def check_background(files: list[Path], bg_files: list[Path]) -> None:
    """An option takes one value: ``--background a.png b.png`` would make b.png a laser image."""
    both = sorted(set(map(Path.resolve, files)) & set(map(Path.resolve, bg_files)))
    if both:
        raise LightplaneError(f"{both[0]} is both a laser image and a --background frame (give --background once per "
                              "file, or one folder or quoted glob)")


@app.command("calibrate-plane-board")
@handles_errors
def calibrate_plane_board_cmd(
    images: List[str] = typer.Argument(..., help="Laser-on chessboard images, one board pose each (files, folders, globs)."),
    camera: Path = typer.Option(..., "--camera", help="Camera file (JSON, ROS YAML or OpenCV YAML/XML)."),
    board: str = typer.Option(..., "--board", help="Inner corners, COLSxROWS (e.g. 9x6)."),
    square: float = typer.Option(..., "--square", help="Square size in mm."),
    output: Path = typer.Option(..., "-o", "--output", help="Light-plane JSON file to write."),
    background: Optional[List[str]] = typer.Option(None, "--background", help="Laser-off frames (file, folder or glob; "
                                                   "repeat the option): one per image, same order, or one for all."),
    stripe_width: Optional[float] = typer.Option(None, "--stripe-width", help="Stripe width in px (default: estimated)."),
    channel: Optional[str] = typer.Option(None, "--channel", help="Colour channel of the laser: red, green, blue, gray."),
    rotate: int = typer.Option(0, "--rotate", help="Rotate every image clockwise by 0/90/180/270 degrees first."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing output file."),
) -> None:
    """Calibrate the light plane with a chessboard in two or more poses (Zhou's method, the paper's baseline)."""
    from ..baselines.zhou import calibrate_plane_board
    from ..camera import Camera

    cols, rows = parse_board(board)
    if not square > 0:
        raise LightplaneError(f"--square must be positive, got {square} mm")
    check_output(output, force)
    cam = Camera.load(camera)
    files, imgs = read_images(images, "images", rotate)
    if len(files) < 2:
        raise LightplaneError(f"Zhou's method needs at least 2 board poses (images), got {len(files)}")
    bg_files, bgs = read_images(background, "background images", rotate) if background else ([], None)
    check_background(files, bg_files)
    if bgs is not None and len(bgs) not in (1, len(imgs)):
        raise LightplaneError(f"--background: give one laser-off frame or one per image ({len(imgs)}), got {len(bgs)}")

    with Progress(TextColumn("board poses and stripes"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=True) as bar:
        task = bar.add_task("images", total=len(imgs))
        res = calibrate_plane_board(imgs, cam, (cols, rows), square, background_images=bgs,
                                    image_names=[str(f) for f in files], stripe_width_px=stripe_width,
                                    channel=channel, progress=lambda i: bar.update(task, completed=i + 1))

    pl = res.plane
    sd = np.sqrt(np.diag(pl.covariance))
    t = Table(title="Light plane, Zhou's planar-target method (camera frame)", show_edge=False)
    for c, j in (("coefficient", "left"), ("value", "right"), ("± std", "right"), ("unit", "left")):
        t.add_column(c, justify=j)
    for name, v, s, u in zip("abcd", pl.coefficients, sd, ("-", "-", "-", "mm")):
        t.add_row(name, f"{v:+.6f}" if u == "-" else f"{v:+.4f}", f"{s:.2g}", u)
    console.print(t)
    sigma_deg = float(np.degrees(np.sqrt(np.trace(pl.covariance[:3, :3]))))
    console.print(f"normal direction σ ≈ {sigma_deg:.4f} deg (covariance: {pl.meta['covariance_method']})")
    console.print(f"{len(res.points_cam_mm)} stripe points from {len(set(res.view_index.tolist()))} board poses, "
                  f"residual RMS {res.residual_rms_mm:.4f} mm")
    v = Table(title="Per image", show_edge=False)
    for c in ("image", "stripe points", "pose RMS (px)", "residual RMS (mm)", "board distance (mm)"):
        v.add_column(c, justify="left" if c == "image" else "right")
    for im in pl.meta["images"]:
        r = im.get("residual_rms_mm")
        v.add_row(Path(im["name"]).name, str(im["n_stripe_points"]) + ("" if im["used"] else " (unused)"),
                  f"{im['reprojection_rms_px']:.3f}", "-" if r is None else f"{r:.4f}",
                  f"{np.linalg.norm(im['t_cam_board_mm']):.1f}")
    console.print(v)
    opts = {"board": f"{cols}x{rows}", "square_mm": square, "stripe_width_px": stripe_width, "channel": channel,
            "rotate_deg": rotate, "background": [str(f) for f in bg_files], "camera": str(camera)}
    pl.save(output, force=force, extra={"provenance": provenance(files, opts)})
    console.print(f"wrote {output}")
