"""``lightplane render``: synthetic images with exact ground truth (circle, chessboard, any target, scan)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import typer

from lightplane.core.errors import LightplaneError
from lightplane.cli._common import (app, console, dictionary_option, dot_option, handles_errors, marker_option, parse_board,
                      progress_bar, target_option)
from lightplane.camera.targets import Target, parse_target
from lightplane.plane.model import LightPlane
from lightplane.simulate.render import (CALIBRATION_CAPTURE, STRIPE_CAPTURE, BoardOptions, CircleOptions, Dataset,
                                        check_output_dir, render_chessboard_dataset, render_circle_dataset,
                                        render_scan_dataset, render_target_dataset, second_laser_plane)
from lightplane.simulate.turntable import TurntableScanOptions, render_turntable_board, render_turntable_scan

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
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed: same seed, same bytes."),
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
    req = _Request(scene, n, seed, difficulty, polarity, diameter, stripe, laser_off, dark_laser, kind, step, lasers,
                   turntable_step, square)
    if scene == "target":
        req = replace(req, target=parse_target(board, square, marker_mm=marker, dictionary=dictionary, dot_mm=dot,
                                               target_file=target_file))
    elif board is not None:
        req = replace(req, board=parse_board(board))
    # fail before the long render: the folder must be writable and hold no result files
    check_output_dir(out, ["camera.json", "truth.json"], force)
    t0 = time.perf_counter()
    with progress_bar(f"rendering {scene}", n) as update:
        ds = _render(req, lambda i, total: update(i, total=total))
    elapsed = time.perf_counter() - t0
    ds.save(out, force=force)
    cam = ds.camera
    console.print(f"rendered {len(ds.images)} {scene} image(s) of {cam.width}x{cam.height} px in {elapsed:.1f} s "
                  f"(seed {seed}, difficulty {ds.truth.get('difficulty')})")
    _describe(req, ds)
    console.print(f"wrote {out}/ (images, camera.json, truth.json)")


@dataclass(frozen=True)
class _Request:
    """What the command was asked to render (its options as given)."""

    scene: str
    n: int | None
    seed: int
    difficulty: str | None
    polarity: str
    diameter: float
    stripe: bool
    laser_off: bool
    dark_laser: bool
    kind: str
    step: float | None
    lasers: int | None
    turntable_step: float | None
    square: float | None
    board: tuple[int, int] | None = None
    target: Target | None = None


def _render(req: _Request, progress) -> Dataset:
    """The data set of ``req``: its scene's options object, then the scene's renderer."""
    n, seed = req.n, req.seed
    if req.scene == "circle":
        circle = CircleOptions(difficulty=req.difficulty or "realistic", polarity=req.polarity,
                               diameter_mm=req.diameter, laser_off=req.laser_off,
                               more_planes=(second_laser_plane(),) if req.lasers == 2 else ())
        return render_circle_dataset(12 if n is None else n, seed, circle, progress=progress)
    if req.scene == "target":
        opts = BoardOptions(difficulty=req.difficulty or "realistic", with_stripe=req.stripe, laser_off=req.laser_off,
                            dark_laser=req.dark_laser)
        return render_target_dataset(req.target, (6 if req.stripe else 30) if n is None else n, seed, opts,
                                     progress=progress)
    if req.scene == "chessboard":
        design = STRIPE_CAPTURE if req.stripe else CALIBRATION_CAPTURE
        capture = replace(design, board=design.board if req.board is None else req.board,
                          square_mm=design.square_mm if req.square is None else req.square)
        opts = BoardOptions(difficulty=req.difficulty or "clean", capture=capture, with_stripe=req.stripe,
                            laser_off=req.laser_off)
        return render_chessboard_dataset(20 if n is None else n, seed, opts, progress=progress)
    if req.scene == "turntable":
        tt = TurntableScanOptions(difficulty=req.difficulty or "clean", step_deg=req.turntable_step,
                                  lasers=2 if req.lasers is None else req.lasers)
        return render_turntable_scan(24 if n is None else n, seed, tt, progress=progress)
    if req.scene == "turntable-board":
        k = 7 if n is None else n
        return render_turntable_board(angles_deg=np.linspace(-40.0, 40.0, k) if k > 1 else [0.0], seed=seed,
                                      difficulty=req.difficulty or "clean")
    return render_scan_dataset(kind=req.kind, n_frames=n, step_mm=req.step, seed=seed,
                               difficulty=req.difficulty or "realistic", progress=progress)


def _describe(req: _Request, ds: Dataset) -> None:
    """Print what was rendered, per scene."""
    if req.scene == "circle":
        bad = [e["file"] for e in ds.truth["images"] if not e["usable"]]
        console.print(f"target diameter {req.diameter:g} mm, polarity {req.polarity}; "
                      f"{len(ds.truth['images']) - len(bad)} usable" + (f", unusable: {', '.join(bad)}" if bad else ""))

        for las in ds.truth.get("lasers", []):
            console.print(f"  {las['name']} ({las['channel']} channel): plane {LightPlane.from_dict(las['plane'])}")
    elif req.scene == "chessboard":
        b = ds.truth["board"]
        console.print(f"board {b['inner_corners'][0]}x{b['inner_corners'][1]} inner corners, square {b['square_mm']:g} mm"
                      + (", laser stripe on" if req.stripe else ""))
    elif req.scene == "target":
        assert req.target is not None  # parsed for this scene
        console.print(f"board: {req.target.describe()}" + (", laser stripe on" if req.stripe else "")
                      + (" (dark laser frames)" if req.dark_laser and req.stripe else ""))
    elif req.scene == "turntable":
        t = ds.truth
        console.print(f"turntable scan of a {t['sphere']['radius_mm']:g} mm sphere: {len(t['angles_deg'])} frames per laser, "
                      f"{t['step_deg']:g} deg per frame, lasers {', '.join(t['lasers'])}; true axis in truth.json")
    elif req.scene == "turntable-board":
        console.print(f"chessboard 9x6, 8 mm, standing on the turntable at {len(ds.images)} angles; true axis in truth.json")
    else:
        m = ds.truth["motion"]
        console.print(f"scan of a {req.kind}: {m['n_frames']} frames, {m['step_mm']:g} mm per frame")
