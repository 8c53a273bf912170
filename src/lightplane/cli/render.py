"""``lightplane render``: synthetic images with exact ground truth (circle, chessboard, any target, scan)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import typer

from lightplane.core.errors import LightplaneError
from lightplane.cli._common import (app, console, dictionary_option, dot_option, handles_errors, marker_option, parse_board,
                      progress_bar, target_option)
from lightplane.camera.targets import parse_target
from lightplane.plane.model import LightPlane
from lightplane.simulate.render import (check_output_dir, render_chessboard_dataset, render_circle_dataset,
    render_scan_dataset, render_target_dataset, second_laser_plane)
from lightplane.simulate.turntable import render_turntable_board, render_turntable_scan

SCENES = ("circle", "chessboard", "target", "scan", "turntable", "turntable-board")


@app.command("render")
@handles_errors
def render_cmd(
    scene: Literal["circle", "chessboard", "target", "scan", "turntable", "turntable-board"] = typer.Argument(
        ..., help="What to render: circle, chessboard, target (any board: --board KIND:COLSxROWS --square MM, or "
        "--target FILE), scan, turntable (a sphere on a turntable, one frame per angle and laser) or "
        "turntable-board (a chessboard standing on the turntable, for calibrate-turntable)."),
    out: Path = typer.Option(..., "--out", help="Output folder (created if its parent exists)."),
    n: Optional[int] = typer.Option(None, "--n", min=1, help="Number of images (scan: frames). Default: 12 circle, "
                                    "20 chessboard, 41 sphere / 21 step or plane frames."),
    seed: int = typer.Option(0, "--seed", help="Random seed: same seed, same bytes."),
    difficulty: Optional[Literal["clean", "realistic", "hard"]] = typer.Option(None, "--difficulty", help="clean, realistic or hard "
                                             "(default: realistic; clean for chessboards)."),
    polarity: Literal["light", "dark"] = typer.Option("light", "--polarity", help="circle: light disc on dark background, or dark "
                                 "printed disc on a light board."),
    diameter: float = typer.Option(50.0, "--diameter", help="circle: disc diameter in mm."),
    board: Optional[str] = typer.Option(None, "--board", help="chessboard: inner corners COLSxROWS (default: 15x11 "
                                        "for the calibration capture, 9x6 with --stripe); target: KIND:COLSxROWS."),
    square: Optional[float] = typer.Option(None, "--square", help="chessboard: square size in mm (default 8); "
                                           "target: square size or dot pitch."),
    marker: Optional[float] = marker_option,
    dictionary: Optional[str] = dictionary_option,
    dot: Optional[float] = dot_option,
    target_file: Optional[Path] = target_option,
    stripe: bool = typer.Option(False, "--stripe", help="chessboard, target: laser on, stripe crossing every board."),
    laser_off: bool = typer.Option(False, "--laser-off", help="circle, and chessboard/target with --stripe: also a "
                                   "laser-off image of every pose (a laser-off or pattern frame)."),
    dark_laser: bool = typer.Option(False, "--dark-laser", help="target with --stripe: the laser frames dark "
                                    "(3 % of the ambient light: the board cannot be found in them)."),
    kind: Literal["sphere", "step", "plane"] = typer.Option("sphere", "--kind", help="scan: sphere (radius 25.4 mm), step (10.000 mm gauge) "
                             "or plane (tilted)."),
    step: Optional[float] = typer.Option(None, "--step", help="scan: motion per frame in mm (default 1.5 sphere, "
                                         "2.0 step/plane)."),
    lasers: Optional[int] = typer.Option(None, "--lasers", min=1, max=2, help="turntable: 1 or 2 lasers (frames of "
                                         "their own; default 2). circle: 2 renders a second laser whose stripe crosses "
                                         "the first on the disc (colour images: laser0 red, laser1 green; calibrate "
                                         "with --laser laser0=red --laser laser1=green; default 1)."),
    turntable_step: Optional[float] = typer.Option(None, "--turntable-step", help="turntable: degrees per frame "
                                                   "(default: one turn over --n frames)."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing files."),
) -> None:
    """Render synthetic images with exact ground truth (PNG images, camera.json, truth.json)."""
    if not diameter > 0:
        raise LightplaneError(f"--diameter must be positive, got {diameter} mm")
    if square is not None and not square > 0:
        raise LightplaneError(f"--square must be positive, got {square} mm")
    if step is not None and not step > 0:
        raise LightplaneError(f"--step must be positive, got {step} mm")
    tgt = None
    if scene == "target":
        tgt = parse_target(board, square, marker_mm=marker, dictionary=dictionary, dot_mm=dot,
                           target_file=target_file)
        cols_rows = None
    else:
        cols_rows = parse_board(board) if board is not None else None
    # fail before the long render: the folder must be writable and hold no result files
    check_output_dir(out, ["camera.json", "truth.json"], force)

    t0 = time.perf_counter()
    with progress_bar(f"rendering {scene}", n) as update:

        def progress(i: int, total: int) -> None:
            update(i, total=total)

        if scene == "circle":
            ds = render_circle_dataset(n=12 if n is None else n, seed=seed, difficulty=difficulty or "realistic",
                                       polarity=polarity, diameter_mm=diameter, laser_off=laser_off,
                                       progress=progress,
                                       more_planes=[second_laser_plane()] if lasers == 2 else [])
        elif scene == "target":
            ds = render_target_dataset(tgt, n=(6 if stripe else 30) if n is None else n, seed=seed,
                                       difficulty=difficulty or "realistic", with_stripe=stripe, laser_off=laser_off,
                                       dark_laser=dark_laser, progress=progress)
        elif scene == "chessboard":
            ds = render_chessboard_dataset(n=20 if n is None else n, seed=seed, board=cols_rows, square_mm=square,
                                           with_stripe=stripe, laser_off=laser_off, difficulty=difficulty or "clean",
                                           progress=progress)
        elif scene == "turntable":
            ds = render_turntable_scan(n_frames=24 if n is None else n, step_deg=turntable_step, seed=seed,
                                       difficulty=difficulty or "clean", lasers=2 if lasers is None else lasers,
                                       progress=progress)
        elif scene == "turntable-board":
            k = 7 if n is None else n
            ds = render_turntable_board(angles_deg=np.linspace(-40.0, 40.0, k) if k > 1 else [0.0], seed=seed,
                                        difficulty=difficulty or "clean")
        else:
            ds = render_scan_dataset(kind=kind, n_frames=n, step_mm=step, seed=seed,
                                     difficulty=difficulty or "realistic", progress=progress)
    elapsed = time.perf_counter() - t0
    ds.save(out, force=force)
    cam = ds.camera
    console.print(f"rendered {len(ds.images)} {scene} image(s) of {cam.width}x{cam.height} px in {elapsed:.1f} s "
                  f"(seed {seed}, difficulty {ds.truth.get('difficulty')})")
    if scene == "circle":
        bad = [e["file"] for e in ds.truth["images"] if not e["usable"]]
        console.print(f"target diameter {diameter:g} mm, polarity {polarity}; "
                      f"{len(ds.truth['images']) - len(bad)} usable" + (f", unusable: {', '.join(bad)}" if bad else ""))

        for las in ds.truth.get("lasers", []):
            console.print(f"  {las['name']} ({las['channel']} channel): plane {LightPlane.from_dict(las['plane'])}")
    elif scene == "chessboard":
        b = ds.truth["board"]
        console.print(f"board {b['inner_corners'][0]}x{b['inner_corners'][1]} inner corners, square {b['square_mm']:g} mm"
                      + (", laser stripe on" if stripe else ""))
    elif scene == "target":
        assert tgt is not None  # parsed above for this scene
        console.print(f"board: {tgt.describe()}" + (", laser stripe on" if stripe else "")
                      + (" (dark laser frames)" if dark_laser and stripe else ""))
    elif scene == "turntable":
        t = ds.truth
        console.print(f"turntable scan of a {t['sphere']['radius_mm']:g} mm sphere: {len(t['angles_deg'])} frames per laser, "
                      f"{t['step_deg']:g} deg per frame, lasers {', '.join(t['lasers'])}; true axis in truth.json")
    elif scene == "turntable-board":
        console.print(f"chessboard 9x6, 8 mm, standing on the turntable at {len(ds.images)} angles; true axis in truth.json")
    else:
        m = ds.truth["motion"]
        console.print(f"scan of a {kind}: {m['n_frames']} frames, {m['step_mm']:g} mm per frame")
    console.print(f"wrote {out}/ (images, camera.json, truth.json)")
