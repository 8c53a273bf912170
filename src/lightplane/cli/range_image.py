"""``lightplane range-image``: a linear scan's cloud as a range image (16-bit PNG/TIFF and float X, Y, Z arrays)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

import typer

from lightplane.cli._common import app, console, handles_errors, output_file
from lightplane.core.io import provenance
from lightplane.measure.pointcloud import cloud_comments, read_cloud
from lightplane.measure.rangeimage import RangeImageOptions, range_image, write_range_image


@app.command("range-image")
@handles_errors
def range_image_cmd(
    cloud: Path = typer.Argument(..., help="Point cloud of a linear scan (PLY, CSV or NPY from measure --step or "
                                 "--positions), with each point's frame."),
    output: Path = typer.Option(..., "-o", "--output", help="16-bit range image (.png or .tif); the float X, Y, Z "
                                "arrays go beside it (.npz)."),
    across: Literal["auto", "x", "y", "z"] = typer.Option("auto", "--across", help="The cloud coordinate of the "
                                                          "columns (auto: the one the profiles extend along)."),
    height: Literal["x", "y", "z"] = typer.Option("z", "--height", help="The coordinate of the image's values."),
    step: Optional[float] = typer.Option(None, "--step", help="Column spacing, mm (default: the median point "
                                         "spacing along the profiles)."),
    scale: Optional[float] = typer.Option(None, "--scale", help="Height per 16-bit level, mm (default: the finest "
                                          "1/2/5 x 10^k µm that spans the heights)."),
    force: bool = typer.Option(False, "--force", help="Overwrite the output files."),
) -> None:
    """Resample a linear scan's cloud on a regular grid: one row per frame, one column per STEP mm across.

    The 16-bit image follows SICK's convention (0: no point; height = offset + value x scale, both in the
    image's metadata); the .npz holds HALCON-style X, Y, Z float images (mm, NaN: no point). See
    docs/range-images.md.
    """
    output_file(output, force, inputs=[cloud], suffixes=(".png", ".tif", ".tiff"))
    output_file(output.with_suffix(".npz"), force, inputs=[cloud])
    opts = RangeImageOptions(across=across, height=height, step_mm=step, scale_mm=scale)
    comments = cloud_comments(cloud)
    frame = next((c.split("(", 1)[-1].rstrip(")") for c in comments if c.startswith("lightplane point cloud:")),
                 "the cloud's frame")
    prov = provenance([cloud], {"across": across, "height": height, "step_mm": step, "scale_mm": scale})
    ri = range_image(read_cloud(cloud), opts, frame_description=frame, meta={"provenance": prov})
    paths = write_range_image(output, ri, force=force)
    rows, cols = ri.shape
    filled = float((ri.values() > 0).mean())
    console.print(f"range image {rows} frames x {cols} columns of {ri.step_mm:.4g} mm along {ri.across} "
                  f"(from {ri.origin_mm:.3f} mm); {ri.height} = {ri.offset_mm:.4f} mm + value x {ri.scale_mm:g} mm; "
                  f"{100 * filled:.1f} % of the pixels have a point; coordinates: {frame}")
    for p in paths:
        console.print(f"wrote {p}")
