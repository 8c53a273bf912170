"""One level of parallelism: threading configuration, serial == parallel, batched == per frame.

Correctness only (no timings: those are in benchmarks/bench_load.py).
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import cv2
import numba
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _measure_synth import CAM, PLANE, stripe_image, surface  # noqa: E402

from lightplane.stripe import kernels as K  # noqa: E402
from lightplane.core import threads  # noqa: E402
from lightplane.measure.profile import ProfileMeasurer  # noqa: E402
from lightplane.measure.scan import ArrayFrames, FrameProcessor, iter_scan, scan_points  # noqa: E402
from lightplane.stripe.extract import extract_profile, extract_profiles  # noqa: E402
from lightplane.measure.options import MeasureOptions  # noqa: E402
from lightplane.stripe.options import StripeOptions  # noqa: E402

FIELDS = ("uv", "valid", "intensity", "strength", "width", "normals", "status", "lines")


def roi_stack(n=12, H=48, W=300, seed=3, dtype=np.uint8, scale=200.0):
    """n frames H x W: a tilted, curved Gaussian stripe (its row moving frame to frame), noise 2 levels;
    every third frame without a stripe (noise only), one with a reflection far from it."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(float)
    out = []
    for k in range(n):
        c = 0.5 * H + rng.uniform(-5, 5) + 0.02 * (u - W / 2) + 3.0 * np.sin(u / W * np.pi) - 1.5
        img = 10.0 + rng.normal(0.0, 2.0, (H, W))
        if k % 3 != 2:
            img += scale * np.exp(-0.5 * ((v - c) / 2.1) ** 2)
        if k == 4:
            img += 0.6 * scale * np.exp(-0.5 * ((v - c + 18) / 2.1) ** 2) * (u < 80)
        out.append(np.clip(np.round(img), 0, np.iinfo(dtype).max if dtype != np.float32 else 1e9).astype(dtype))
    return np.stack(out)


def assert_same(a, b):
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), f
    assert (a.axis, a.sigma_px, a.width_px) == (b.axis, b.sigma_px, b.width_px)


@pytest.mark.parametrize("axis", ["columns", "rows"])
def test_batched_profiles_identical_to_per_frame(axis):
    stack = roi_stack()
    if axis == "rows":
        stack = np.ascontiguousarray(stack.transpose(0, 2, 1))
    batch = extract_profiles(stack, axis, StripeOptions(width_px=5.0))
    assert len(batch) == len(stack)
    assert sum(p.valid.sum() for p in batch) > 0.5 * 8 * 300   # the stripe frames are found
    for f, img in enumerate(stack):
        assert_same(batch[f], extract_profile(img, axis, StripeOptions(width_px=5.0)))
    # the width estimated on the first frame is the width of all
    est = extract_profiles(stack, axis)
    for f in (0, 5, 11):
        assert_same(est[f], extract_profile(stack[f], axis, StripeOptions(width_px=est[0].width_px)))


def test_batched_profiles_identical_other_types_roi_and_options():
    u8 = roi_stack(n=6)
    # 16-bit frames whose full scale differs frame to frame (12-bit data, and 16-bit): its own min_peak each
    u16 = (u8.astype(np.uint16) * 16)
    u16[1] *= 8
    f32 = u8.astype(np.float32) / 255.0
    roi = (20, 4, 250, 40)
    for stack in (u16, f32):
        batch = extract_profiles(stack, options=StripeOptions(width_px=5.0, continuity=False, sigma_along_px=3.0),
                                 roi=roi)
        for f, img in enumerate(stack):
            assert_same(batch[f], extract_profile(img,
                                                  options=StripeOptions(width_px=5.0, continuity=False, sigma_along_px=3.0),
                                                  roi=roi))
    # a list of colour frames with a channel goes frame by frame through the same conversions
    bgr = [cv2.merge([img // 4, img // 3, img]) for img in u8]
    batch = extract_profiles(bgr, options=StripeOptions(width_px=5.0, channel="red"))
    for f, img in enumerate(bgr):
        assert_same(batch[f], extract_profile(img, options=StripeOptions(width_px=5.0, channel="red")))
    batch = extract_profiles(bgr, options=StripeOptions(width_px=5.0, channel="red", min_chroma=0.3))
    for f, img in enumerate(bgr):
        assert_same(batch[f], extract_profile(img, options=StripeOptions(width_px=5.0, channel="red", min_chroma=0.3)))


def test_batch_memory_reused_only_when_nothing_holds_it():
    """A batch's outputs share one block; the next batch of that size reuses it only once
    nothing of the last one is alive: profiles held stay intact, a dropped batch's block
    (and no other) comes back; any view of it (one array of one profile) keeps it."""
    from lightplane.stripe.extract import release_batch_memory

    stack = roi_stack()
    other = roi_stack(seed=8)

    def ptr(batch):
        return batch[0].intensity.__array_interface__["data"][0]

    a = extract_profiles(stack, options=StripeOptions(width_px=5.0))
    kept = [(p.uv.copy(), p.normals.copy(), p.status.copy()) for p in a]
    b = extract_profiles(other, options=StripeOptions(width_px=5.0))      # a is alive: new memory
    assert not np.shares_memory(a[0].uv, b[0].uv)
    for p, (uv, nrm, st) in zip(a, kept):
        assert np.array_equal(p.uv, uv, equal_nan=True) and np.array_equal(p.normals, nrm, equal_nan=True)
        assert np.array_equal(p.status, st)
    pb = ptr(b)
    one_view = b[3].width
    del b
    c = extract_profiles(other, options=StripeOptions(width_px=5.0))      # a view of b alive: still new memory
    assert ptr(c) != pb and not np.shares_memory(c[0].uv, one_view)
    pc = ptr(c)
    del c
    d = extract_profiles(stack, options=StripeOptions(width_px=5.0))      # nothing of c alive: its block again, right numbers
    assert ptr(d) == pc
    for p, (uv, nrm, st) in zip(d, kept):
        assert np.array_equal(p.uv, uv, equal_nan=True) and np.array_equal(p.status, st)
    del d
    release_batch_memory()
    e = extract_profiles(stack, options=StripeOptions(width_px=5.0))
    assert len(e) == len(stack)


def test_single_frame_parallel_only_when_large_and_a_core_is_free(monkeypatch):
    monkeypatch.setattr(threads, "idle_cpus", lambda: 1)
    assert threads.profile_parallel(600, 600) == (numba.get_num_threads() > 1)
    assert not threads.profile_parallel(1280, 64) and not threads.profile_parallel(100, 4000)
    monkeypatch.setattr(threads, "idle_cpus", lambda: 0)   # other processes want every core
    assert not threads.profile_parallel(1280, 960)
    monkeypatch.setattr(threads, "idle_cpus", lambda: None)   # unknown: by the size alone
    assert threads.profile_parallel(1280, 960) == (numba.get_num_threads() > 1)


def test_serial_and_parallel_kernels_give_the_same_numbers():
    stack = roi_stack(n=8, H=600, W=600)
    for img in stack[:3]:
        for w in (None, 5.0):
            a = extract_profile(img, options=StripeOptions(width_px=w), parallel=False)
            assert_same(a, extract_profile(img, options=StripeOptions(width_px=w), parallel=True))
            assert_same(a, extract_profile(img, options=StripeOptions(width_px=w)))
    small = roi_stack(n=6)
    a = extract_profiles(small, options=StripeOptions(width_px=5.0), parallel=False)
    b = extract_profiles(small, options=StripeOptions(width_px=5.0), parallel=True)
    for x, y in zip(a, b):
        assert_same(x, y)


def test_serial_profile_launches_no_parallel_kernel(monkeypatch):
    """parallel=False (and serial_kernels) keeps the width estimate serial too (it was not)."""
    img = roi_stack(n=1, H=600, W=600)[0]
    ref = extract_profile(img)

    def boom(*a, **k):
        raise AssertionError("parallel kernel called")

    for name in ("profile_candidates", "profile_centres", "profiles_batch"):
        monkeypatch.setattr(K, name, boom)
    assert_same(ref, extract_profile(img, parallel=False))
    with threads.serial_kernels():
        assert_same(ref, extract_profile(img))
        extract_profiles(roi_stack(n=3), options=StripeOptions(width_px=5.0))


def test_threading_configuration_is_applied():
    info = threads.threading_info()
    if "OMP_WAIT_POLICY" not in os.environ or os.environ["OMP_WAIT_POLICY"] == "PASSIVE":
        assert info["OMP_WAIT_POLICY"] == "PASSIVE"
    assert info["GOMP_SPINCOUNT"] == os.environ["GOMP_SPINCOUNT"]   # a short spin, then sleep
    if "NUMBA_THREADING_LAYER" not in os.environ:
        assert info["numba_layer_priority"][0] == "omp"
        extract_profile(roi_stack(n=1, H=600, W=600)[0], parallel=True)
        assert numba.threading_layer() in ("omp", "tbb", "workqueue")
    n0 = numba.get_num_threads()
    with threads.serial_kernels():
        assert threads.in_serial_context() and numba.get_num_threads() == 1
        assert not threads.profile_parallel(4000, 4000)
    assert not threads.in_serial_context() and numba.get_num_threads() == n0
    c0 = cv2.getNumThreads()
    with threads.frames_across_threads():
        assert cv2.getNumThreads() == 1
        with threads.frames_across_threads():
            assert cv2.getNumThreads() == 1
        assert cv2.getNumThreads() == 1
    assert cv2.getNumThreads() == c0
    assert "numba threading layer" in threads.describe()


def test_import_changes_no_process_setting_and_blas_is_held_only_inside_lightplane():
    """``import lightplane`` leaves the BLAS pools and the OpenMP variables as they were; inside
    :func:`blas_limited` (lightplane's calibrations and scans, the whole command line) the pools are at
    one thread and afterwards back; a user's ``OPENBLAS_NUM_THREADS`` (here 2) stands throughout.
    Fresh interpreters, so that nothing of this process's state counts."""
    import json
    import subprocess

    code = ("import json, os, cv2, scipy.linalg; from threadpoolctl import threadpool_info\n"
            "def pools(): return sorted(d['num_threads'] for d in threadpool_info() if d['user_api'] == 'blas')\n"
            "before = pools(); import lightplane; from lightplane.core import threads\n"
            "after = pools(); omp = [v for v in ('OMP_WAIT_POLICY', 'GOMP_SPINCOUNT', 'KMP_BLOCKTIME') if v in os.environ]\n"
            "with threads.blas_limited():\n    inside = pools()\n"
            "print(json.dumps([before, after, omp, inside, pools()]))")
    env = {k: v for k, v in os.environ.items() if k not in threads._BLAS_ENV + ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT",
                                                                                 "KMP_BLOCKTIME")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    before, after, omp, inside, later = json.loads(out.stdout.strip().splitlines()[-1])
    assert after == before and omp == [], (before, after, omp)
    assert len(inside) >= 2 and all(n == threads.BLAS_THREADS for n in inside), inside
    assert later == before
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OPENBLAS_NUM_THREADS": "2"}, capture_output=True,
                         text=True, check=True)
    before, after, omp, inside, later = json.loads(out.stdout.strip().splitlines()[-1])
    assert inside == before and 2 in inside, (before, inside)


def test_scan_worker_threads_run_serial_kernels():
    n_s, d_s = surface()
    frames = [stripe_image(n_s, d_s, shift_px=0.3 * k)[0] for k in range(6)]
    proc = FrameProcessor(CAM, PLANE, None, MeasureOptions(StripeOptions(width_px=3.5)))
    seen = []
    run_batch = proc.run_batch

    def spy(batch):
        seen.append((threading.current_thread() is threading.main_thread(), threads.in_serial_context(),
                     numba.get_num_threads(), cv2.getNumThreads()))
        return run_batch(batch)

    proc.run_batch = spy
    res = list(iter_scan(ArrayFrames(frames), proc, workers=2, executor="thread", batch=2))
    assert [r.index for r in res] == list(range(6))
    assert seen and all(s == (False, True, 1, 1) for s in seen)
    seen.clear()
    list(iter_scan(ArrayFrames(frames), proc, workers=1))
    assert seen == [] or all(s[1] and s[2] == 1 for s in seen)


def test_measure_batches_a_short_roi_with_the_same_records():
    n_s, d_s = surface()
    imgs = [stripe_image(n_s, d_s, shift_px=0.4 * k) for k in range(5)]
    u = np.concatenate([uc[np.isfinite(uc)] for _, uc in imgs])
    x0 = int(np.floor(u.min())) - 12
    roi = (x0, 0, int(np.ceil(u.max())) + 12 - x0, CAM.height)   # a short band across the stripe (axis rows)
    frames = [im for im, _ in imgs]
    m = ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5), roi=roi))
    assert m.axis == "rows" and m.batches
    many = m.measure_many(frames)
    for f, img in enumerate(frames):
        one = m(img)
        assert np.array_equal(many[f].points, one.points, equal_nan=True)
        assert np.array_equal(many[f].valid, one.valid)
        assert np.array_equal(many[f].sigma_mm, one.sigma_mm, equal_nan=True)
    assert sum(p.valid.sum() for p in many) > 5 * 300
    whole = ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    assert not whole.batches and not ProfileMeasurer(CAM, PLANE, MeasureOptions(roi=roi)).batches   # no width: frame by frame
    # the scan uses it (one process, and worker threads) with the records of frame-by-frame processing
    ref = np.concatenate([FrameProcessor(CAM, PLANE, None, MeasureOptions(StripeOptions(width_px=3.5), roi=roi)).process(i, f) for i, f in enumerate(frames)])
    for workers in (1, 2):
        rec, _ = scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5), roi=roi),
                             workers=workers, executor="thread")
        assert np.array_equal(rec.view(np.uint8), ref.view(np.uint8))


def test_idle_cpus_does_not_count_this_process_own_threads(monkeypatch):
    # 2 CPUs, 3 runnable tasks: busy, unless two of the three are our own threads
    # (numba's workers still falling asleep after the previous kernel)
    monkeypatch.setattr(threads, "_usable_cpus", lambda: 2)
    monkeypatch.setattr(threads, "_runnable_tasks", lambda: 3)
    for own, idle in ((1, -1), (2, 0), (3, 1), (5, 1)):
        monkeypatch.setattr(threads, "_own_running_threads", lambda own=own: own)
        threads._idle_time[0] = -1.0     # no cached reading
        assert threads.idle_cpus() == idle
    monkeypatch.setattr(threads, "_runnable_tasks", lambda: 1)   # only the caller: one core free
    threads._idle_time[0] = -1.0
    assert threads.idle_cpus() == 1
    threads._idle_time[0] = -1.0
    assert threads._own_running_threads() >= 1   # the real reading counts at least the caller


def test_blas_limited_blocks_of_two_threads_restore_the_pools_once_both_end():
    """The BLAS pools are process-wide: a block that ends while another thread's block still runs
    keeps the limit, and the last one to end gives the original setting back.  A fresh interpreter,
    so that no other test's threads or loaded libraries count."""
    import json
    import subprocess

    code = ("import json, threading, cv2, scipy.linalg; from threadpoolctl import threadpool_info\n"
            "from lightplane.core import threads\n"
            "def pools(): return [d['num_threads'] for d in threadpool_info() if d['user_api'] == 'blas']\n"
            "before = pools(); entered, release = threading.Event(), threading.Event()\n"
            "def other():\n"
            "    with threads.blas_limited():\n        entered.set(); release.wait(30)\n"
            "t = threading.Thread(target=other); t.start(); entered.wait(30)\n"
            "with threads.blas_limited():\n    both = pools()\n"
            "still = pools(); release.set(); t.join(30)\n"
            "print(json.dumps([before, both, still, pools()]))")
    env = {k: v for k, v in os.environ.items() if k not in threads._BLAS_ENV}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    before, both, still, after = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(before) >= 2, before
    assert all(n == threads.BLAS_THREADS for n in both), both
    assert all(n == threads.BLAS_THREADS for n in still), still   # the other thread's block still runs
    assert after == before, (before, after)

