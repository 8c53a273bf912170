"""The GenTL source end to end against a real GenTL producer: the simulated camera producer ``viky.cti`` that the
``genicam`` package (harvesters' GenApi/GenTL binding) ships.  It has three cameras (serial numbers 0, 1, 2) that
show a red, green and blue bouncing square on white, 400 x 400 px, Mono8 or RGBa8, 20 frames/s, no exposure, gain,
offsets or timestamps."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.live.genicam import open_genicam
from lightplane.live.source import Source

genicam = pytest.importorskip("genicam", reason="harvesters / genicam (the genicam extra) is not installed")
pytest.importorskip("harvesters", reason="harvesters (the genicam extra) is not installed")
CTI = os.path.join(os.path.dirname(genicam.__file__), "viky.cti")


@pytest.fixture()
def viky():
    if not os.path.isfile(CTI):
        pytest.skip(f"the genicam package at {os.path.dirname(CTI)} ships no viky.cti simulator")
    return CTI


def _ball(image: np.ndarray) -> tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1) of the pixels that are not white."""
    mask = image < 255 if image.ndim == 2 else (image < 255).any(axis=2)
    ys, xs = np.nonzero(mask)
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def test_frames_counters_and_the_square(viky):
    src = open_genicam(f"genicam:{viky}?serial=0&pixel=Mono8&fps=50")
    src.start()
    try:
        assert isinstance(src, Source)
        assert src.nominal_fps == pytest.approx(50.0)
        frames = [src.read(timeout=2.0)]
        dropped_before = src.dropped
        frames += [src.read(timeout=2.0) for _ in range(5)]
        ids = [f.meta["frame_id"] for f in frames]
        # the counter follows the GenTL frame ids
        assert [f.index - frames[0].index for f in frames] == [i - ids[0] for i in ids]
        assert src.dropped - dropped_before == ids[-1] - ids[0] - 5
        boxes = []
        for f in frames:
            assert f.image.shape == (400, 400) and f.image.dtype == np.uint8
            assert set(np.unique(f.image).tolist()) == {0, 255}
            x0, y0, x1, y1 = _ball(f.image)
            assert (f.image[y0:y1, x0:x1] == 0).all()  # one filled square
            assert x1 - x0 == y1 - y0
            boxes.append((x0, y0))
            assert f.meta["timestamp"] == "arrival" and f.t_exposure == f.t_received  # viky has no timestamps
        assert len(set(boxes)) > 1  # it moves
    finally:
        src.stop()


def test_colours_roi_and_missing_controls(viky):
    for serial, bgr in (("0", (0, 0, 255)), ("2", (255, 0, 0))):
        src = open_genicam(f"genicam:{viky}?serial={serial}&pixel=RGBa8&roi=0,0,320,240")
        src.start()
        try:
            f = src.read(timeout=2.0)
            assert f.image.shape == (240, 320, 3) and f.meta["pixel_format"] == "RGBa8"
            colours = {tuple(c) for c in np.unique(f.image.reshape(-1, 3), axis=0).tolist()}
            assert colours == {(255, 255, 255), bgr}  # camera 0 red, camera 2 blue, in BGR order
            assert src.controls()["roi"].value == (0, 0, 320, 240)
            assert "exposure_us" not in src.controls()
            with pytest.raises(LightplaneError, match="has no exposure_us"):
                src.set_control("exposure_us", 100.0)
            with pytest.raises(LightplaneError, match="no OffsetX/OffsetY"):
                src.set_control("roi", (8, 8, 64, 64))
            src.set_control("pixel_format", "Mono8")  # restarts the stream
            f = src.read(timeout=2.0)
            f = src.read(timeout=2.0)
            assert f.image.shape == (240, 320)
        finally:
            src.stop()


def test_dropped_frames_are_counted(viky):
    src = open_genicam(f"genicam:{viky}?serial=1&pixel=Mono8&fps=100&buffers=2")
    src.start()
    try:
        first = src.read(timeout=2.0)
        dropped_before = src.dropped
        time.sleep(0.5)  # ~50 frames pass while the two buffers are full
        frames = [src.read(timeout=2.0) for _ in range(6)]
        gaps = sum(b.index - a.index - 1 for a, b in zip([first] + frames, frames))
        assert gaps > 0 and src.dropped - dropped_before == gaps
    finally:
        src.stop()


def test_spec_forms():
    a = open_genicam("genicam:/opt/p.cti?serial=5&roi=0,0,64,32&exposure=100").options
    b = open_genicam("/opt/p.cti,serial=5,roi=0:0:64:32", exposure_us=100.0).options
    assert a == b and a.cti == "/opt/p.cti" and a.roi == (0, 0, 64, 32) and a.serial == "5"


def test_missing_camera_producer_and_bad_specs(viky, tmp_path):
    with pytest.raises(LightplaneError, match=r"no camera with serial '7' behind viky.cti; cameras found: Viky #0"):
        open_genicam(f"genicam:{viky}?serial=7").start()
    with pytest.raises(LightplaneError, match="does not exist"):
        open_genicam(f"genicam:{tmp_path / 'none.cti'}").start()
    bogus = tmp_path / "bogus.cti"
    bogus.write_bytes(b"not a library")
    with pytest.raises(LightplaneError, match="could not be loaded|cameras found: none"):
        open_genicam(f"genicam:{bogus}").start()
    for spec, msg in [("genicam:", "needs the GenTL producer"), ("genicam:x.cti?shutter=1", "unknown genicam option"),
                      ("genicam:x.cti?roi=1,2", "roi is x,y,w,h"), ("genicam:x.cti,roi=1:2", "roi is x,y,w,h")]:
        with pytest.raises(LightplaneError, match=msg):
            open_genicam(spec)


def test_controls_change_while_another_thread_reads(viky):
    import threading

    src = open_genicam(f"genicam:{viky}?serial=0&pixel=Mono8&fps=50")
    src.start()
    shapes, errors, stop = [], [], threading.Event()

    def reader():
        while not stop.is_set():
            try:
                shapes.append(src.read(timeout=2.0).image.shape)
            except Exception as e:  # noqa: BLE001 - the test reports whatever the reader met
                errors.append(e)
                return

    t = threading.Thread(target=reader)
    t.start()
    try:
        time.sleep(0.2)
        src.set_control("roi", (0, 0, 200, 100))  # stops and restarts the acquisition under the reader
        time.sleep(0.3)
    finally:
        stop.set()
        t.join(timeout=5.0)
        src.stop()
    assert not errors, errors
    assert shapes[0] == (400, 400) and shapes[-1] == (100, 200)
