"""``lightplane measure-batch``: many scans (a manifest CSV) on a Dask cluster → one Parquet dataset."""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, Optional

import typer

from lightplane.core.errors import LightplaneError
from lightplane.cli._common import app, console, err_console, fail, handles_errors
from lightplane.cli.measure import parse_roi
from lightplane.core.io import summarize_reasons
from lightplane.measure.batch import BatchOptions, measure_batch, read_manifest, require_extra
from lightplane.measure.options import MeasureOptions
from lightplane.measure.scan import Dropped
from lightplane.stripe.options import StripeOptions

#: per-scan progress bars up to this many scans (then the overall bar only)
MAX_SCAN_BARS = 12


@app.command("measure-batch")
@handles_errors
def measure_batch_cmd(
    manifest: Path = typer.Argument(..., help="Manifest CSV: header id,input,camera,plane[,step,direction,positions,background]; "
                                    "direction written x;y;z; relative paths from the manifest's folder."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder: points/scan=<id>/part-<k>.parquet, "
                                "manifest.json (created; re-running resumes; one run at a time)."),
    local_workers: Optional[int] = typer.Option(None, "--local-workers", help="Start N single-threaded worker "
                                                "processes on this machine (a Dask LocalCluster)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of a running Dask scheduler, "
                                            "tcp://HOST:PORT (workers must see the same paths)."),
    chunk_frames: int = typer.Option(200, "--chunk-frames", help="Frames per task (a scan is split into chunks)."),
    ply: bool = typer.Option(False, "--ply", help="Also write one PLY per scan (ply/<id>.ply)."),
    roi: Optional[str] = typer.Option(None, "--roi", help="Region X0,Y0,X1,Y1 in px (X1, Y1 exclusive), all scans."),
    axis: str = typer.Option("auto", "--axis", help="One centre per 'columns', 'rows', or 'auto' (from the plane)."),
    channel: Optional[str] = typer.Option(None, "--channel", help="Colour channel of the laser: red, green, blue, gray."),
    stripe_width: Optional[float] = typer.Option(None, "--stripe-width", help="Stripe width (FWHM) px; default: "
                                                 "estimated on each scan's first frame."),
    smooth: int = typer.Option(0, "--smooth", help="Smooth the centres along the stripe over N lines (odd >= 5; 0: off)."),
    sigma_along: Optional[float] = typer.Option(None, "--sigma-along", help="Gaussian scale along the stripe, px "
                                                "(as in measure)."),
    break_lock: bool = typer.Option(False, "--break-lock", help="Take the output folder's lock whoever holds it "
                                    "(only when the run named by the lock is known to be gone, e.g. on another host)."),
) -> None:
    """Measure every scan of a manifest on a Dask cluster; the same points as `measure`, bit for bit.

    Each scan's frames are cut into chunks of --chunk-frames; each chunk is one task that
    reads its own frames and writes one Parquet partition atomically.  Re-running the same
    command skips the partitions already complete and measured with the same frames,
    calibration files, options and code.  One run at a time per output folder (a lock
    file).  A scan that fails (missing input, unreadable calibration, wrong frame size) is
    reported, its partitions set aside, and the others go on; exit 2 only when no scan could
    be measured.
    """
    require_extra()

    if (local_workers is None) == (scheduler is None):
        raise LightplaneError("give either --local-workers N or --scheduler tcp://HOST:PORT")
    if local_workers is not None and local_workers < 1:
        raise LightplaneError(f"--local-workers must be >= 1, got {local_workers}")
    if chunk_frames < 1:
        raise LightplaneError(f"--chunk-frames must be >= 1, got {chunk_frames}")
    if axis not in ("auto", "columns", "rows"):
        raise LightplaneError(f"--axis must be auto, columns or rows, got {axis!r}")
    options = MeasureOptions(StripeOptions(width_px=stripe_width, channel=channel, sigma_along_px=sigma_along),
                             axis=axis, roi=parse_roi(roi) if roi is not None else None, smooth_lines=smooth)
    scans = read_manifest(manifest)
    with _batch_progress(len(scans)) as progress, _terminate_as_interrupt():
        r = measure_batch(scans, output, options,
                          BatchOptions(chunk_frames=chunk_frames, ply=ply, break_lock=break_lock),
                          scheduler=scheduler, local_workers=local_workers, progress=progress,
                          on_dashboard=_print_dashboard, on_notice=_print_notice)
    _print_batch(r, scans)
    if r.set_aside:
        err_console.print(f"set aside: {len(r.set_aside)} folder(s) or file(s) of failed or dropped scans in "
                          f"{Path(output) / 'set-aside'} (listed in manifest.json)")
    console.print(f"wrote {Path(output) / 'points'} and {Path(output) / 'manifest.json'} (status {r.status})")
    if not any(s["status"] == "ok" for s in r.scans):
        fail(f"no scan could be measured ({len(r.failed)} failed; see above and {Path(output) / 'manifest.json'})")


@contextmanager
def _batch_progress(n_scans: int) -> Iterator[Callable[[str, int, int], None]]:
    """Transient progress bars: all scans' chunks, and each scan's up to :data:`MAX_SCAN_BARS` scans;
    yields ``progress(scan_id, chunks_done, chunks_total)``."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=True) as bar:
        overall = bar.add_task("all scans (chunks)", total=None)
        per_scan: dict = {}
        state: dict = {}

        def progress(sid: str, done: int, total: int) -> None:
            state[sid] = (done, total)
            if n_scans <= MAX_SCAN_BARS:
                if sid not in per_scan:
                    per_scan[sid] = bar.add_task(f"scan {sid}", total=total)
                bar.update(per_scan[sid], completed=done, total=total)
            bar.update(overall, completed=sum(d for d, _ in state.values()),
                       total=sum(t for _, t in state.values()))

        yield progress


@contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt for the block (as Ctrl-C does), so that the run releases its
    lock and marks its manifest before the command ends (exit 130)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _print_notice(line: str) -> None:
    err_console.print(f"warning: {line}")


def _print_dashboard(link) -> None:
    console.print(f"Dask dashboard: {link}" if link else "Dask dashboard: not available (install bokeh)")


def _print_batch(r, scans) -> None:
    """What :func:`measure_batch` did: totals, skipped frames, failed scans."""
    ok = [s for s in r.scans if s["status"] == "ok"]
    console.print(f"{len(ok)} of {len(r.scans)} scans measured: {r.n_frames} frames, {r.n_points} points, "
                  f"{r.partitions_written} partitions written, {r.partitions_reused} already complete, "
                  f"{r.seconds:.1f} s ({r.n_frames / max(r.seconds, 1e-9):.0f} frames/s)")
    for s in r.scans:
        if s["skipped"]:
            err_console.print(f"warning: scan {s['id']}: {len(s['skipped'])} unreadable frame(s) skipped: "
                              + summarize_reasons([(name, why) for _, name, why in s["skipped"]]))
        summary = Dropped(totals=s.get("dropped", {}), n_frames_without_stripe=s.get("frames_without_stripe", 0)).summary()
        if summary:
            console.print(f"scan {s['id']}: {summary} (per frame: manifest.json)")
    for s in r.failed:
        err_console.print(f"failed: scan {s['id']} (manifest row {_row(scans, s['id'])}): {s['error']}")


def _row(scans, sid: str) -> int:
    return next((s.row for s in scans if s.id == sid), 0)
