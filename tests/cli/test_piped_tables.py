"""Tables printed into a pipe or a file keep every cell whole (file names are not cut to fit 80 columns)."""

from __future__ import annotations

import io

from rich.table import Table

from lightplane.cli._common import console


def test_a_wide_table_into_a_pipe_is_printed_whole(monkeypatch):
    buf = io.StringIO()  # not a terminal
    monkeypatch.setattr(console, "file", buf)
    names = [f"calibration_8x10/calibration_{k:03d}_laser0_dark_frame.jpg" for k in range(3)]
    t = Table(title="Per image used", show_edge=False)
    for c in ("image", "stripe points", "pose RMS (px)", "residual RMS (mm)", "board distance (mm)"):
        t.add_column(c)
    for n in names:
        t.add_row(n, "812", "0.670", "0.0829", "112.7")
    console.print(t)
    out = buf.getvalue()
    assert all(n in out for n in names) and "…" not in out
    assert max(map(len, out.splitlines())) > 80  # as wide as it needs
    console.print("a line")  # the console's width is back for what follows
    assert console.width == 80 or console.is_terminal
