"""The paper's §3 simulation study (lightplane.evaluate.study) and `lightplane simulate`."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from lightplane import LightplaneError
from lightplane.cli import app
from lightplane.evaluate.study import FACTORS, METHODS, run_factor

runner = CliRunner()


def _rows(res, method):
    return [r for r in res.rows if r["method"] == method]


def test_noise_factor_noise_free_exact_and_bound_linear_in_sigma():
    res = run_factor("noise", trials=2, seed=3, n_rim=60, n_stripe=60)
    levels = FACTORS["noise"].levels
    assert len(res.rows) == len(levels) * (len(METHODS) + 1)
    for m in METHODS:
        r0 = _rows(res, m)[0]
        assert r0["level"] == 0 and r0["failed"] == 0
        assert r0["angle_deg"] < 1e-8 and r0["offset_mm"] < 1e-8 and r0["rel_coef_pct"] < 1e-8
    bound = _rows(res, "crlb")
    assert bound[0]["angle_deg"] == 0
    # the same placements at every level (common random numbers): the bound is linear in sigma
    for r in bound[1:]:
        np.testing.assert_allclose(r["angle_deg"] / r["sigma_px"], bound[1]["angle_deg"] / 0.1, rtol=1e-9)
        np.testing.assert_allclose(r["tri_rms_mm"] / r["sigma_px"], bound[1]["tri_rms_mm"] / 0.1, rtol=1e-9)


def test_placements_factor_bound_falls_with_more_placements():
    res = run_factor("placements", trials=2, seed=1, n_rim=60, n_stripe=60, methods=("ml",))
    bound = [r["angle_deg"] for r in _rows(res, "crlb")]
    # each level adds placements to the same ones: Fisher information only grows
    assert all(b2 < b1 for b1, b2 in zip(bound, bound[1:]))
    assert [r["n_placements"] for r in _rows(res, "ml")] == list(range(2, 8))


def test_run_factor_rejects_bad_arguments():
    with pytest.raises(LightplaneError, match="factor"):
        run_factor("speed")
    with pytest.raises(LightplaneError, match="trials"):
        run_factor("noise", trials=0)
    with pytest.raises(LightplaneError, match="method"):
        run_factor("noise", trials=1, methods=("magic",))


def test_cli_writes_csv_png_json_and_refuses_overwrite(tmp_path):
    out = tmp_path / "study"
    r = runner.invoke(app, ["simulate", "diameter", "--out", str(out), "--trials", "1", "--rim-points", "40",
                            "--stripe-points", "40", "--seed", "5"])
    assert r.exit_code == 0, r.output
    with open(out / "diameter.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(FACTORS["diameter"].levels) * 4
    assert {"angle_deg", "offset_mm", "rel_coef_pct", "tri_rms_mm", "failed"} <= set(rows[0])
    assert (out / "diameter.png").read_bytes()[:4] == b"\x89PNG"
    meta = json.loads((out / "study.json").read_text())
    assert meta["provenance"]["options"]["seed"] == 5
    before = (out / "diameter.csv").read_bytes()
    r = runner.invoke(app, ["simulate", "diameter", "--out", str(out), "--trials", "1"])
    assert r.exit_code == 2
    assert (out / "diameter.csv").read_bytes() == before


@pytest.mark.parametrize("args, message", [
    (["simulate", "bogus", "--out", "{tmp}"], "'bogus' is not one of 'placements', 'noise', 'diameter', 'all'"),
    (["simulate", "noise", "--out", "{tmp}", "--trials", "0"], "'--trials': Input should be greater than or equal to 1"),
    (["simulate", "noise", "--out", "{tmp}", "--rim-points", "2"], "--rim-points"),
])
def test_cli_bad_arguments_exit_2(tmp_path, args, message, capfd):
    args = [a.replace("{tmp}", str(tmp_path / "o")) for a in args]
    r = runner.invoke(app, args)
    assert r.exit_code == 2
    assert message in capfd.readouterr().err + r.output


def test_cli_subprocess_exit_status_and_one_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    p = subprocess.run([sys.executable, "-m", "lightplane", "simulate", "noise", "--out", str(blocker)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert p.stderr.strip().count("\n") == 0 and "not a folder" in p.stderr
