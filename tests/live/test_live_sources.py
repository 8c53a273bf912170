"""Live frame sources: fixed-rate replays count the frames a slow reader misses; specs open the right source."""

from __future__ import annotations

import time

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.live.simulated import SimulatedSensor
from lightplane.live.source import Source
from lightplane.live.sources import (REPLAY_QUEUE, SCHEMES, ArraySource, FolderSource, VideoSource, open_source, parse_options,
                                     register_scheme)


def frames(n: int = 5, shape=(24, 32)) -> list[np.ndarray]:
    return [np.full(shape, i, np.uint8) for i in range(n)]


def test_replay_at_its_rate_drops_what_a_slow_reader_misses():
    src = ArraySource(frames(), fps=100.0, queue=1)
    assert isinstance(src, Source)
    src.start()
    a = src.read()
    time.sleep(0.105)  # ten periods and a bit: the replay went on without the reader
    b = src.read()
    assert a is not None and b is not None
    assert b.index - a.index - 1 == src.dropped >= 9
    # frame k is exposed at t0 + k / fps: the times say which frames were skipped
    assert b.t_exposure - a.t_exposure == pytest.approx((b.index - a.index) / 100.0, abs=1e-9)
    assert int(b.image[0, 0]) == b.index % 5  # looped: the frame counter runs on, the images repeat
    assert b.t_received >= b.t_exposure


def test_replay_keeps_its_rate_and_drops_nothing_for_a_fast_reader():
    src = ArraySource(frames(3), fps=20.0, loop=True)
    src.start()
    t0 = time.monotonic()
    got = [src.read() for _ in range(5)]
    assert time.monotonic() - t0 >= 4 / 20.0 - 1e-3
    assert [f.index for f in got if f is not None] == list(range(5)) and src.dropped == 0


def test_replay_once_ends_and_without_a_rate_delivers_every_frame():
    src = ArraySource(frames(3), fps=None, loop=False)
    src.start()
    out = [src.read(), src.read(), src.read(), src.read()]
    assert [int(f.image[0, 0]) for f in out[:3] if f is not None] == [0, 1, 2] and out[3] is None
    assert src.dropped == 0


def test_replay_queues_frames_for_a_late_reader_as_a_camera_driver():
    """With a queue of 4 (the default), a reader 2.5 periods late gets every frame, oldest first, each with its
    own exposure time; 10 periods late, the frames pushed out of the queue are dropped and counted."""
    assert REPLAY_QUEUE == 4
    src = ArraySource(frames(), fps=50.0)
    src.start()
    a = src.read()
    time.sleep(0.05)  # 2.5 periods: frames 1 and 2 are exposed and queued
    got = [src.read() for _ in range(3)]
    assert a is not None and [f.index for f in got] == [1, 2, 3] and src.dropped == 0
    assert all(f.t_received - f.t_exposure >= 0 for f in got)
    assert got[0].t_exposure == pytest.approx(a.t_exposure + 0.02, abs=1e-9)
    time.sleep(0.2)  # 10 periods: only the newest 4 are still queued
    b = src.read()
    assert b is not None
    newest = int(np.floor((b.t_received - a.t_exposure) * 50.0))  # frames exposed since frame 0, at most
    assert newest - 4 <= b.index <= newest - 3 and src.dropped == b.index - 4


def test_a_late_reader_of_a_finite_replay_counts_the_frames_it_never_got():
    src = ArraySource(frames(4), fps=100.0, loop=False)
    src.start()
    time.sleep(0.2)  # the whole replay is over before the first read
    assert src.read() is None and src.dropped == 4


def test_folder_in_natural_order(tmp_path):
    import cv2

    for i in (10, 2, 1):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((8, 8), i, np.uint8))
    src = open_source(str(tmp_path), fps=None, loop=False)
    assert isinstance(src, FolderSource)
    src.start()
    vals = []
    while (f := src.read()) is not None:
        vals.append(int(f.image[0, 0]))
    assert vals == [1, 2, 10]


def test_video_file(tmp_path):
    import cv2

    path = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (32, 24))
    if not w.isOpened():
        pytest.skip("OpenCV here cannot write MJPG video")
    for i in range(6):
        w.write(np.full((24, 32, 3), 40 * i, np.uint8))
    w.release()
    src = open_source(str(path), fps=None, loop=False)
    assert isinstance(src, VideoSource) and src.nominal_fps == pytest.approx(25.0)  # the file's own rate
    src.start()
    got = []
    while (f := src.read()) is not None:
        got.append(float(f.image.mean()))
    src.stop()
    assert len(got) == 6 and all(abs(g - 40 * i) < 8 for i, g in enumerate(got))  # MJPG is lossy
    src.start()  # a stopped video starts again from its first frame
    again = src.read()
    src.stop()
    assert again is not None and again.index == 0 and abs(float(again.image.mean()) - got[0]) < 1e-9


def test_specs():
    sim = open_source("sim:linear,fps=12,scale=0.25,object=step")
    assert isinstance(sim, SimulatedSensor) and sim.nominal_fps == 12.0 and sim.camera.width == 320
    assert sim.hardware.has_stage and not sim.hardware.has_turntable
    assert parse_options("a=1, b=2.5,c=true,d=x") == {"a": 1, "b": 2.5, "c": True, "d": "x"}
    for spec, words in (("nope:3", "unknown scheme"), ("/no/such/thing.avi", "no such"), ("", "no source"),
                        ("sim:cube", "kind"), ("sim:turntable,bogus=1", "no option .bogus."), ("sim:target,lasers=2", "one laser"), ("sim:turntable,fps", "key=value"), ("sim:turntable,fps=-1", "fps")):
        with pytest.raises(LightplaneError, match=words):
            open_source(spec)
    with pytest.raises(LightplaneError, match="cannot be opened|no camera"):
        open_source("uvc:97")
    # GenICam cameras by their transport: the sources come back unstarted (nothing opened yet)
    from lightplane.live.aravis import AravisSource
    from lightplane.live.genicam import GenICamSource

    assert isinstance(open_source("aravis:127.0.0.1,exposure=5000"), AravisSource)
    assert isinstance(open_source("genicam:/no/such/producer.cti"), GenICamSource)
    with pytest.raises(LightplaneError, match="unknown aravis option"):
        open_source("aravis:cam,bogus=1")
    try:
        register_scheme("mine", lambda rest, **kw: ArraySource(frames(), name=rest))
        assert open_source("mine:abc").name.startswith("abc")
    finally:
        SCHEMES.pop("mine", None)


class FakeCapture:
    """Stands for ``cv2.VideoCapture`` of a V4L2 camera at 50 frames/s whose driver lost frames 3 and 4:
    buffer time stamps (ms, monotonic clock) as OpenCV's V4L2 backend gives them."""

    def __init__(self, *args) -> None:
        self.stamps = [k * 20.0 for k in (0, 1, 2, 5, 6)]
        self.i = -1
        self.props: dict = {}
        self.t0 = time.monotonic() * 1000.0

    def isOpened(self) -> bool:
        return True

    def read(self):
        self.i += 1
        return True, np.full((4, 4), self.i, np.uint8)

    def get(self, prop):
        import cv2

        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.t0 - 200.0 + self.stamps[self.i]
        if prop == cv2.CAP_PROP_FPS:
            return 50.0
        return self.props.get(prop, 0.0)

    def set(self, prop, value) -> bool:
        import cv2

        if prop == cv2.CAP_PROP_GAIN and value < 0:
            return False  # the driver refuses it
        self.props[prop] = value
        return True

    def release(self) -> None:
        pass


def test_uvc_camera_counts_the_frames_its_driver_lost(monkeypatch):
    import cv2

    monkeypatch.setattr(cv2, "VideoCapture", FakeCapture)
    src = open_source("/dev/video7", exposure=100)
    assert src.name == "uvc:/dev/video7" and src.nominal_fps == 50.0 and src.controls()["exposure"].value == 100
    src.start()
    frames = [src.read() for _ in range(5)]
    assert [f.index for f in frames] == [0, 1, 2, 5, 6] and src.dropped == 2
    assert np.allclose(np.diff([f.t_exposure for f in frames]), [0.02, 0.02, 0.06, 0.02])
    assert all(f.t_received > f.t_exposure for f in frames)
    with pytest.raises(LightplaneError, match="refuses gain"):
        src.set_control("gain", -1)
    with pytest.raises(LightplaneError, match="no control 'zoom'"):
        src.set_control("zoom", 2)
