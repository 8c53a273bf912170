"""The Aravis source end to end against Aravis' own simulated GigE Vision camera (arv-fake-gv-camera-0.8) on the
loopback interface: frames arrive with growing counters, the images are exactly what the fake camera generates,
exposure / gain / region of interest / pixel format are set, dropped frames are counted, a missing camera is one
LightplaneError.  The pixel conversions and the counter are also checked without Aravis."""

from __future__ import annotations

import shutil
import subprocess
import time

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.live.aravis import PIXEL_FORMATS, FrameCounter, convert_pixels, open_aravis
from lightplane.live.source import Source

FAKE = "arv-fake-gv-camera-0.8"
SERIAL = "LPTEST"
DEVICE = f"Aravis-Fake-{SERIAL}"


# --- without Aravis ----------------------------------------------------------------------------------------------
def test_frame_counter_unwraps_16_bit_ids_and_counts_gaps():
    c = FrameCounter(wrap=65535)
    assert [c.advance(i) for i in (65533, 65534, 65535, 1, 2)] == [0, 1, 2, 3, 4]  # id 0 is never sent
    assert c.dropped == 0
    assert c.advance(5) == 7 and c.dropped == 2  # ids 3 and 4 lost
    c = FrameCounter(wrap=65535)
    c.advance(65534)
    assert c.advance(2) == 3 and c.dropped == 2  # 65535 and 1 lost across the wrap
    c64 = FrameCounter(wrap=None)
    assert [c64.advance(i) for i in (70000, 70001, 70004)] == [0, 1, 4] and c64.dropped == 2


def _mosaic(pattern: str, rgb: tuple[int, int, int], h: int = 8, w: int = 10) -> np.ndarray:
    value = dict(zip("RGB", rgb))
    bottom = {"RG": "GB", "BG": "GR", "GR": "BG", "GB": "RG"}[pattern]
    cell = np.array([[value[c] for c in pattern], [value[c] for c in bottom]], np.uint8)
    return np.tile(cell, (h // 2, w // 2))


@pytest.mark.parametrize("code", [c for c, (_, kind, _) in PIXEL_FORMATS.items() if kind.startswith("bayer_")])
def test_bayer_patterns_follow_the_genicam_names(code):
    name, kind, bits = PIXEL_FORMATS[code]
    raw = _mosaic(kind[-2:], (200, 120, 40)).astype(np.uint8 if bits == 8 else np.uint16)
    if bits == 16:
        raw = raw * 64  # e.g. 12-bit values in 16-bit words
    bgr = convert_pixels(raw.astype(raw.dtype.newbyteorder("<")).tobytes(), 10, 8, code)
    assert bgr.shape == (8, 10, 3) and bgr.dtype == raw.dtype
    scale = 1 if bits == 8 else 64
    # a uniform colour comes back exactly inside the border: blue, green, red
    assert bgr[2:-2, 2:-2].reshape(-1, 3).tolist() == [[40 * scale, 120 * scale, 200 * scale]] * (4 * 6)


def test_mono_rgb_and_refused_formats():
    mono16 = np.arange(12, dtype="<u2").reshape(3, 4) * 1000
    out = convert_pixels(mono16.tobytes(), 4, 3, 0x01100007)
    assert out.dtype == np.uint16 and np.array_equal(out, mono16)
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    assert np.array_equal(convert_pixels(rgb.tobytes(), 3, 2, 0x02180014), rgb[:, :, ::-1])
    assert np.array_equal(convert_pixels(rgb.tobytes(), 3, 2, 0x02180015), rgb)
    with pytest.raises(LightplaneError, match="0x010c0006 is not supported"):  # Mono12Packed
        convert_pixels(b"\0" * 9, 2, 3, 0x010C0006)
    with pytest.raises(LightplaneError, match="needs 24 bytes, got 10"):
        convert_pixels(b"\0" * 10, 4, 3, 0x01100007)


def test_aravis_spec_errors():
    src = open_aravis("aravis:Cam-1?exposure=2000&gain=3&roi=0,0,64,32&fps=30&pixel=Mono8&buffers=4")
    o = src.options
    assert (o.device, o.exposure_us, o.gain_db, o.roi, o.frame_rate_hz, o.n_buffers) == \
        ("Cam-1", 2000.0, 3.0, (0, 0, 64, 32), 30.0, 4)
    # the same with the options after commas, without the scheme, and overridden by keywords
    src = open_aravis("Cam-1,exposure=2000,roi=0:0:64:32,buffers=4", gain=3, frame_rate_hz=30.0)
    assert src.options == o.__class__(**{**o.__dict__, "pixel_format": None})
    for spec, msg in [("aravis:x?roi=1,2,3", "roi is x,y,w,h"), ("aravis:x?shutter=3", "unknown aravis option"),
                      ("aravis:x?exposure=-1", "exposure_us must be > 0"), ("aravis:x,exposure", "write key=value"),
                      ("aravis:x?timestamps=gps", "timestamps must be")]:
        with pytest.raises(LightplaneError, match=msg):
            open_aravis(spec)


# --- against the fake camera ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fake_camera():
    if shutil.which(FAKE) is None:
        pytest.skip(f"{FAKE} is not installed (Debian package aravis-tools)")
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as e:
        pytest.skip(f"Aravis is not available to Python: {e} (gir1.2-aravis-0.8 and PyGObject)")
    from lightplane.live.aravis import aravis_devices

    proc = subprocess.Popen([FAKE, "-i", "127.0.0.1", "-s", SERIAL], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 10.0
        while DEVICE not in aravis_devices():
            if proc.poll() is not None:
                out = proc.stdout.read().decode(errors="replace").strip() if proc.stdout else ""
                pytest.skip(f"{FAKE} did not start on 127.0.0.1 ({out}); is another fake camera running?")
            if time.monotonic() > deadline:
                pytest.fail(f"{FAKE} started but Aravis did not find {DEVICE} within 10 s")
            time.sleep(0.2)
        yield DEVICE
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()


def _ramp(frame_id: int, shape: tuple[int, int], scale: float = 1.0) -> np.ndarray:
    """What the fake camera generates in Mono8: ((x + y + frame id) mod 255) x scale, clipped to 0..255."""
    y, x = np.mgrid[:shape[0], :shape[1]]
    return np.clip(((x + y + frame_id) % 255) * scale, 0, 255).astype(np.uint8)


@pytest.fixture()
def source(fake_camera):
    src = open_aravis(f"aravis:{fake_camera}?fps=100&pixel=Mono8&exposure=10000&gain=0&roi=0,0,256,128")
    src.start()
    yield src
    src.stop()


def test_frames_arrive_with_counters_and_the_generated_image(source):
    assert isinstance(source, Source)
    assert source.nominal_fps == pytest.approx(100.0)
    frames = [source.read(timeout=2.0)]
    dropped_before = source.dropped  # frames lost before the first one delivered are not between two of them
    frames += [source.read(timeout=2.0) for _ in range(5)]
    ids = [f.meta["frame_id"] for f in frames]
    idx = [f.index for f in frames]
    assert all(b > a for a, b in zip(idx, idx[1:]))
    # the counter follows the camera's block ids (unwrapped), and every gap is counted as dropped
    assert [b - a for a, b in zip(idx, idx[1:])] == [(b - a) % 65535 for a, b in zip(ids, ids[1:])]
    assert source.dropped - dropped_before == sum(b - a - 1 for a, b in zip(idx, idx[1:]))
    for f in frames:
        assert f.image.shape == (128, 256) and f.image.dtype == np.uint8
        assert np.array_equal(f.image, _ramp(f.meta["frame_id"], (128, 256)))
        assert f.t_exposure <= f.t_received and f.t_received - f.t_exposure < 1.0
        assert f.meta["pixel_format"] == "Mono8"
    assert source.statistics()["n_completed_buffers"] >= 6


def test_dropped_frames_are_counted(source):
    first = source.read(timeout=2.0)
    dropped_before = source.dropped
    time.sleep(0.5)  # ~50 frames at 100 fps while only 8 buffers circulate: the camera's frames are lost
    frames = [source.read(timeout=2.0) for _ in range(12)]
    gaps = sum(b.index - a.index - 1 for a, b in zip([first] + frames, frames))
    assert gaps > 0 and source.dropped - dropped_before == gaps
    stats = source.statistics()
    assert stats["n_underruns"] > 0 or stats["n_failures"] > 0


def _expect_scale(source, before: float, after: float) -> None:
    """Frames already queued show the old setting; each frame shows the old or the new one, and the new one takes
    over within the buffers in flight and stays."""
    seen = []
    for _ in range(source.options.n_buffers + 4):
        f = source.read(timeout=2.0)
        if np.array_equal(f.image, _ramp(f.meta["frame_id"], f.image.shape, after)):
            seen.append("new")
        else:
            assert np.array_equal(f.image, _ramp(f.meta["frame_id"], f.image.shape, before)), "neither setting"
            seen.append("old")
    assert seen[-3:] == ["new"] * 3 and "old" not in seen[seen.index("new"):], seen


def test_exposure_gain_and_roi(source):
    c = source.controls()
    assert c["exposure_us"].unit == "µs" and c["gain_db"].unit == "dB"
    source.set_control("gain_db", 1.0)  # the fake camera scales its ramp by 1 + gain + log10(exposure / 10 ms)
    _expect_scale(source, before=1.0, after=2.0)
    assert source.controls()["gain_db"].value == pytest.approx(1.0)
    source.set_control("gain_db", 0.0)
    _expect_scale(source, before=2.0, after=1.0)
    source.set_control("exposure_us", 100000.0)
    assert source.controls()["exposure_us"].value == pytest.approx(100000.0)
    _expect_scale(source, before=1.0, after=2.0)
    source.set_control("exposure_us", 10000.0)
    source.set_control("roi", (16, 8, 96, 40))
    f = source.read(timeout=2.0)
    assert f.image.shape == (40, 96)
    assert source.controls()["roi"].value == (16, 8, 96, 40)
    assert np.array_equal(f.image, _ramp(f.meta["frame_id"], (40, 96)))  # the fake ignores the offsets
    with pytest.raises(LightplaneError, match="no control 'focus'"):
        source.set_control("focus", 1.0)


def test_pixel_formats_from_the_camera(source):
    source.set_control("pixel_format", "Mono16")
    f = source.read(timeout=2.0)
    y, x = np.mgrid[:128, :256]
    assert f.image.dtype == np.uint16
    assert np.array_equal(f.image, ((256 * (x + y + f.meta["frame_id"])) % 65535).astype(np.uint16))
    source.set_control("pixel_format", "RGB8")
    f = source.read(timeout=2.0)
    assert f.image.shape == (128, 256, 3) and f.image.dtype == np.uint8
    # the fake camera colours its ramp with a jet colour map: every pixel of one ramp value has one colour (a wrong
    # stride or channel order would break this), blue at the bottom of the map, red at its top
    idx = _ramp(f.meta["frame_id"], (128, 256))
    jet = np.zeros((255, 3), np.int64)
    jet[idx] = f.image
    assert np.array_equal(f.image, jet[idx])
    assert jet[0][0] > 100 and jet[0][2] == 0 and jet[254][2] > 100 and jet[254][0] == 0  # BGR order
    rgb_jet = jet[:, ::-1]  # the map as R, G, B
    for fmt in ("BayerBG8", "BayerGR8", "BayerGB8", "BayerRG8"):
        source.set_control("pixel_format", fmt)
        f = source.read(timeout=2.0)
        assert f.meta["pixel_format"] == fmt and f.image.shape == (128, 256, 3) and f.image.dtype == np.uint8
        assert np.abs(f.image[:, :, 0].astype(int) - f.image[:, :, 2]).mean() > 50  # a colour image
    # GenICam's BayerRG: the sample at (even x, even y) is red and stays the red channel there (demosaicing keeps
    # the samples; OpenCV's border pixels aside).  This fake camera writes the map's blue at those sites and its red
    # at the odd/odd ones, i.e. its "BayerRG8" mosaic is R/B swapped against GenICam's naming.
    idx = _ramp(f.meta["frame_id"], (128, 256))
    inner = (slice(1, -1), slice(1, -1))
    assert np.array_equal(f.image[0::2, 0::2, 2][inner], rgb_jet[idx[0::2, 0::2], 2][inner])
    assert np.array_equal(f.image[1::2, 1::2, 0][inner], rgb_jet[idx[1::2, 1::2], 0][inner])
    assert np.array_equal(f.image[0::2, 1::2, 1][inner], rgb_jet[idx[0::2, 1::2], 1][inner])


def test_missing_camera_is_one_error(fake_camera):
    src = open_aravis("aravis:Aravis-Fake-NOSUCHCAM")
    with pytest.raises(LightplaneError, match=rf"no Aravis camera 'Aravis-Fake-NOSUCHCAM'.*found: .*{DEVICE}"):
        src.start()
    with pytest.raises(LightplaneError, match="is not started"):
        src.read(timeout=0.1)


def test_controls_change_while_another_thread_reads(source):
    import threading

    shapes, errors, stop = [], [], threading.Event()

    def reader():
        while not stop.is_set():
            try:
                shapes.append(source.read(timeout=2.0).image.shape)
            except Exception as e:  # noqa: BLE001 - the test reports whatever the reader met
                errors.append(e)
                return

    t = threading.Thread(target=reader)
    t.start()
    try:
        time.sleep(0.2)
        source.set_control("roi", (0, 0, 64, 48))  # restarts the stream under the reader
        time.sleep(0.3)
        source.set_control("pixel_format", "RGB8")
        time.sleep(0.3)
    finally:
        stop.set()
        t.join(timeout=5.0)
    assert not errors, errors
    assert shapes[0] == (128, 256) and shapes[-1] == (48, 64, 3) and (48, 64) in shapes
