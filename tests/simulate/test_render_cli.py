"""`lightplane render`, the Dataset files, determinism and the hard-level truth."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from lightplane.cli import app
from lightplane.core.errors import LightplaneError
from lightplane.simulate.scene import default_camera, default_plane, sample_placements
from lightplane.simulate.render import (
    BoardOptions,
    CircleOptions,
    render_chessboard_dataset,
    render_circle_dataset,
    render_circle_image,
    render_scan_dataset,
)

runner = CliRunner()


def _err(result) -> str:
    try:
        return result.stderr
    except ValueError:  # older click mixes the streams
        return result.output


@pytest.mark.parametrize(
    "args, message",
    [
        (["render", "cube", "--out", "{out}"], "'cube' is not one of 'circle', 'chessboard', 'target', 'scan'"),
        (["render", "circle", "--out", "{out}", "--n", "0"], "'--n': Input should be greater than or equal to 1"),
        (["render", "circle", "--out", "{out}", "--n", "-3"], "'--n': Input should be greater than or equal to 1"),
        (["render", "circle", "--out", "{out}", "--seed", "-1"], "'--seed': Input should be greater than or equal to 0"),
        (["simulate", "--seed", "-1"], "'--seed': Input should be greater than or equal to 0"),
        (["demo", "--seed", "-1", "--out", "{out}"], "'--seed': Input should be greater than or equal to 0"),
        (["render", "circle", "--out", "{out}", "--difficulty", "extreme"], "--difficulty"),
        (["render", "circle", "--out", "{out}", "--polarity", "grey"], "--polarity"),
        (["render", "scan", "--out", "{out}", "--kind", "cone"], "--kind"),
        (["render", "chessboard", "--out", "{out}", "--board", "9by6"], "--board"),
        (["render", "circle", "--out", "{missing}/deeper"], "does not exist"),
    ],
)
def test_cli_bad_arguments(tmp_path, args, message):
    out = tmp_path / "out"
    argv = [a.format(out=out, missing=tmp_path / "nope") for a in args]
    result = runner.invoke(app, argv)
    assert result.exit_code == 2, result.output
    err = _err(result)
    assert message in err and err.count("\n") == 1
    assert not out.exists() and not (tmp_path / "nope").exists()


def test_cli_unwritable_folder(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    result = runner.invoke(app, ["render", "circle", "--out", str(afile), "--n", "1"])
    assert result.exit_code == 2 and "not a folder" in _err(result)
    assert afile.read_text() == "x"
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        result = runner.invoke(app, ["render", "circle", "--out", str(ro / "sub"), "--n", "1"])
        if os.geteuid() != 0:  # root writes anywhere: nothing to check there
            assert result.exit_code == 2 and "not writable" in _err(result)
            assert not (ro / "sub").exists()
    finally:
        ro.chmod(0o700)
    if os.path.isdir("/proc"):  # a folder that cannot hold files at all, even for root
        result = runner.invoke(app, ["render", "circle", "--out", "/proc/lightplane-render-test", "--n", "1"])
        assert result.exit_code == 2 and "not writable" in _err(result)


def test_cli_renders_and_refuses_to_overwrite(tmp_path):
    out = tmp_path / "scan"
    result = runner.invoke(app, ["render", "scan", "--kind", "step", "--n", "2", "--out", str(out), "--seed", "4"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["camera.json", "scan_000.png", "scan_001.png", "truth.json"]
    truth = json.loads((out / "truth.json").read_text())
    assert truth["kind"] == "step" and len(truth["frames"]) == 2
    top, base = truth["frames"][0]["surfaces"]["top"], truth["frames"][0]["surfaces"]["base"]
    assert np.allclose(top["normal"], base["normal"]) and abs(abs(top["d"] - base["d"]) - 10.0) < 1e-9
    before = (out / "scan_000.png").read_bytes()
    result = runner.invoke(app, ["render", "scan", "--kind", "step", "--n", "2", "--out", str(out), "--seed", "5"])
    assert result.exit_code == 2 and "already exists" in _err(result)
    assert (out / "scan_000.png").read_bytes() == before
    result = runner.invoke(app, ["render", "scan", "--kind", "step", "--n", "2", "--out", str(out), "--seed", "5",
                                 "--force"])
    assert result.exit_code == 0 and (out / "scan_000.png").read_bytes() != before


def test_same_seed_same_bytes():
    a = render_circle_dataset(2, 7, CircleOptions(difficulty="hard"))
    b = render_circle_dataset(2, 7, CircleOptions(difficulty="hard"))
    c = render_circle_dataset(1, 8, CircleOptions(difficulty="hard"))
    assert all(np.array_equal(x, y) for x, y in zip(a.images, b.images))
    assert not np.array_equal(a.images[0], c.images[0])
    assert a.truth["images"][0]["target"]["center_mm"].tobytes() == b.truth["images"][0]["target"]["center_mm"].tobytes()


def test_hard_level_truth():
    ds = render_circle_dataset(3, 2, CircleOptions(difficulty="hard"))
    entries = ds.truth["images"]
    bad = [e for e in entries if not e["usable"]]
    assert len(bad) == 1 and bad[0]["target"]["chord_mm"] is None and "misses" in bad[0]["reason"]
    plane = default_plane()
    for img, e in zip(ds.images, entries):
        assert 2 <= len(e["scene"]["clutter"]) <= 4
        if e["usable"]:
            chord = np.asarray(e["target"]["chord_mm"])
            assert np.allclose(plane.signed_distance(chord), 0, atol=1e-9)
            # the chord's ends are on the rim
            c, r = np.asarray(e["target"]["center_mm"]), e["target"]["diameter_mm"] / 2
            assert np.allclose(np.linalg.norm(chord - c, axis=1), r, atol=1e-9)
        if e["scene"]["saturated_stripe"]:
            # saturated on the stripe only: the disc itself stays well below 255
            uv = ds.camera.project(chord.mean(axis=0)[None])[0]
            assert img[int(round(uv[1])), int(round(uv[0]))] == 255
            assert np.mean(img == 255) < 0.01
    assert any(e["scene"]["saturated_stripe"] for e in entries)


def test_clean_unsaturated_and_dark_polarity_levels():
    cam, plane = default_camera(), default_plane()
    tp = sample_placements(1, np.random.default_rng(0))[0]
    light = render_circle_image(cam, plane, tp, np.random.default_rng(0), CircleOptions(difficulty="clean"))
    dark = render_circle_image(cam, plane, tp, np.random.default_rng(0), CircleOptions(difficulty="clean", polarity="dark"))
    centre = np.round(cam.project(tp.center[None])[0]).astype(int)
    assert light.max() < 255 and dark.max() < 255
    # light disc on dark background vs dark disc on light board
    assert light[centre[1], centre[0]] > 3 * light[5, 5] or light[centre[1], centre[0]] > 100
    ring = cam.project((tp.center + 1.3 * tp.radius_mm * tp.basis()[:, 0])[None])[0].round().astype(int)
    assert dark[ring[1], ring[0]] > 2 * dark[centre[1], centre[0]]


def test_chessboard_stripe_and_laser_off_pairs():
    ds = render_chessboard_dataset(2, 1, BoardOptions(with_stripe=True, laser_off=True))
    assert ds.names == ["board_000.png", "board_000_off.png", "board_001.png", "board_001_off.png"]
    plane = default_plane()
    for k, v in enumerate(ds.truth["views"]):
        seg = np.asarray(v["stripe_on_board_mm"])
        assert np.allclose(plane.signed_distance(seg), 0, atol=1e-9)
        on, off = ds.images[2 * k].astype(int), ds.images[2 * k + 1].astype(int)
        uv = ds.camera.project(seg[0] + np.linspace(0, 1, 50)[:, None] * (seg[1] - seg[0])).round().astype(int)
        diff = on - off
        assert np.median(diff[uv[:, 1], uv[:, 0]]) > 5 and diff[uv[:, 1], uv[:, 0]].max() > 40  # the stripe is there
        assert np.abs(diff[:40, :40]).max() < 10  # and only there


def test_sphere_scan_truth():
    ds = render_scan_dataset("sphere", n_frames=3, step_mm=5.0, seed=0)
    m = ds.truth["motion"]
    c = [np.asarray(f["surfaces"]["sphere"]["center_mm"]) for f in ds.truth["frames"]]
    assert np.allclose(np.linalg.norm(c[1] - c[0]), 5.0) and np.allclose(c[2] - c[1], c[1] - c[0])
    assert np.allclose((c[1] - c[0]) / 5.0, m["direction"])
    # the middle frame's centre lies on the light plane: the stripe cuts a great circle
    assert abs(default_plane().signed_distance(c[1])[0]) < 1e-9
    assert ds.truth["frames"][0]["surfaces"]["sphere"]["radius_mm"] == 25.4


def test_api_bad_input():
    with pytest.raises(LightplaneError, match="difficulty"):
        render_circle_dataset(1, options=CircleOptions(difficulty="easy"))
    with pytest.raises(LightplaneError, match="n must be"):
        render_circle_dataset(n=0)
    with pytest.raises(LightplaneError, match="kind"):
        render_scan_dataset("cube")


def test_dataset_save_round_trip(tmp_path):
    ds = render_circle_dataset(1, 3, CircleOptions(difficulty="clean"))
    ds.save(tmp_path / "c")
    img = cv2.imread(str(tmp_path / "c" / "circle_000.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(img, ds.images[0])
    truth = json.loads((tmp_path / "c" / "truth.json").read_text())
    e = truth["images"][0]
    C = np.asarray(e["target"]["conic_undistorted_px"])
    from lightplane import Camera

    cam = Camera.load(tmp_path / "c" / "camera.json")
    assert cam == ds.camera
    # rim points (from the saved centre/normal/diameter) lie on the saved conic
    n = np.asarray(e["target"]["normal"])
    c = np.asarray(e["target"]["center_mm"])
    e1 = np.cross(n, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    t = np.linspace(0, 2 * np.pi, 50)
    rim = c + e["target"]["diameter_mm"] / 2 * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))
    uv = np.column_stack([cam.project(rim, distort=False), np.ones(50)])
    assert np.abs(np.einsum("ni,ij,nj->n", uv, C, uv)).max() < 1e-9
    assert "provenance" in truth
    with pytest.raises(LightplaneError, match="already exists"):
        ds.save(tmp_path / "c")


@pytest.mark.parametrize("difficulty", ["clean", "realistic"])
def test_noise_matches_the_imaging_model(difficulty):
    """Pixel noise on the flat disc: variance = level / gain + read² + 1/12 (quantisation)."""
    from lightplane.simulate.render import _IMAGING

    cam, plane = default_camera(), default_plane()
    tp = sample_placements(1, np.random.default_rng(4))[0]
    img = render_circle_image(cam, plane, tp, np.random.default_rng(0), CircleOptions(difficulty=difficulty), laser=False).astype(float)
    uv = np.round(cam.project(tp.center[None])[0]).astype(int)
    patch = img[uv[1] - 40:uv[1] + 40, uv[0] - 40:uv[0] + 40]
    # differences of horizontal neighbours: noise is added after the PSF, so it is white
    var = np.var(np.diff(patch, axis=1)) / 2
    im = _IMAGING[difficulty]
    expected = patch.mean() / im.gain_e_per_dn + im.read_noise_dn**2 + 1 / 12
    assert var == pytest.approx(expected, rel=0.15)


def test_plane_scan_stripe_on_truth_line():
    """The stripe on the tilted plane lies on the projected intersection of the two planes."""
    ds = render_scan_dataset("plane", n_frames=1, seed=0, difficulty="clean")
    surf = ds.truth["frames"][0]["surfaces"]["plane"]
    n1, d1 = np.asarray(surf["normal"]), surf["d"]
    lp = default_plane()
    direction = np.cross(n1, lp.normal)
    # a point on both planes
    A = np.array([n1, lp.normal, direction])
    p0 = np.linalg.solve(A, [-d1, -lp.d, 0.0])
    pts = p0 + np.linspace(-60, 60, 400)[:, None] * direction / np.linalg.norm(direction)
    uv = ds.camera.project(pts)
    uv = uv[ds.camera.in_image(uv, margin=20)]
    img = ds.images[0].astype(float)
    offsets = []
    for u, v in uv[::10]:
        row = img[int(round(v)), int(round(u)) - 15:int(round(u)) + 16]
        w = np.clip(row - np.median(img), 0, None)
        offsets.append(np.sum(np.arange(-15, 16) * w) / np.sum(w) + int(round(u)) - u)
    offsets = np.array(offsets)
    assert len(offsets) > 10
    # noise and sampling: well under half a pixel on every row, unbiased on average
    print("plane scan stripe offsets: rms", np.sqrt(np.mean(offsets**2)), "mean", offsets.mean())
    assert np.abs(offsets).max() < 0.5 and abs(offsets.mean()) < 0.1


def test_sphere_scan_stripe_triangulates_onto_the_sphere():
    """Stripe centres of the mid-scan frame, triangulated with the true plane, lie on the sphere."""
    from lightplane.plane.triangulate import triangulate

    ds = render_scan_dataset("sphere", n_frames=1, seed=0, difficulty="clean")
    cam, plane = ds.camera, default_plane()
    s = ds.truth["frames"][0]["surfaces"]["sphere"]
    c, r = np.asarray(s["center_mm"]), s["radius_mm"]
    img = ds.images[0].astype(float)
    us = np.arange(cam.width)
    found = []
    for v in range(0, cam.height, 4):
        rays = cam.rays(np.column_stack([us, np.full(us.size, v)]), unit=True)
        b = rays @ c
        on_sphere = b * b - (c @ c - r * r) > 0  # the pixel's ray meets the sphere
        row = np.where(on_sphere, img[v], 0.0)
        u0 = int(np.argmax(row))
        if row[u0] < 60 or u0 < 8 or u0 > cam.width - 9 or not on_sphere[u0 - 8:u0 + 9].all():
            continue
        win = np.arange(u0 - 6, u0 + 7)
        w = np.clip(img[v, win] - 4.0, 0, None)  # 4 grey levels of ambient light
        found.append((np.sum(win * w) / np.sum(w), v))
    p = triangulate(cam, plane, np.array(found))
    err = np.linalg.norm(p - c, axis=1) - r
    print("sphere stripe points", len(found), "radial error rms mm", np.sqrt(np.mean(err**2)), "mean", err.mean())
    assert len(found) > 50
    assert np.sqrt(np.mean(err**2)) < 0.02 and abs(err.mean()) < 0.01


def test_circle_laser_off_companions():
    ds = render_circle_dataset(1, 5, CircleOptions(difficulty="realistic", laser_off=True))
    assert ds.names == ["circle_000.png", "circle_000_off.png"]
    on, off = ds.images[0].astype(int), ds.images[1].astype(int)
    chord = np.asarray(ds.truth["images"][0]["target"]["chord_mm"])
    uv = ds.camera.project(chord[0] + np.linspace(0.2, 0.8, 30)[:, None] * (chord[1] - chord[0])).round().astype(int)
    assert np.median((on - off)[uv[:, 1], uv[:, 0]]) > 30  # the stripe only in the laser-on image
    far = (on - off)[:100, :100]
    assert abs(far.mean()) < 0.5 and 0 < far.std() < 5  # same scene, independent noise
