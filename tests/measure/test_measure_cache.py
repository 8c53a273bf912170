"""measure_profile's cache of measurers and the lazily built lookup tables of ProfileMeasurer."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _measure_synth import CAM, PLANE, stripe_image, surface  # noqa: E402

from lightplane import Camera, LightPlane, LightplaneError  # noqa: E402
from lightplane.measure import profile as M  # noqa: E402
from lightplane.measure.profile import ProfileMeasurer, clear_profile_cache, measure_profile, profile_cache_info  # noqa: E402
from lightplane.measure.options import MeasureOptions  # noqa: E402
from lightplane.stripe.options import StripeOptions  # noqa: E402


def same(a, b) -> bool:
    """Two profiles equal bit for bit (NaN where NaN)."""
    return all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
               for f in ("points", "sigma_mm", "uv", "valid", "intensity", "width_px", "width_rejected"))


@pytest.fixture(autouse=True)
def fresh_cache():
    clear_profile_cache()
    yield
    clear_profile_cache()


@pytest.fixture(scope="module")
def frames():
    return [stripe_image(*surface(tilt_deg=t, z_mm=z))[0] for t, z in ((20, 455), (10, 450), (30, 460))]


def copy_camera(cam: Camera, **change) -> Camera:
    kw = dict(K=np.array(cam.K), dist=np.array(cam.dist), width=cam.width, height=cam.height)
    kw.update(change)
    return Camera(**kw)


def plane_with_cov(plane: LightPlane) -> LightPlane:
    cov = np.diag([1e-8, 1e-8, 1e-8, 1e-4])
    return LightPlane(plane.normal, plane.d, cov)


def test_cached_equals_uncached_bit_for_bit(frames):
    pl = plane_with_cov(PLANE)
    for img in frames:
        fresh = ProfileMeasurer(CAM, pl, MeasureOptions(StripeOptions(width_px=3.5)))(img)
        assert same(measure_profile(img, CAM, pl, MeasureOptions(StripeOptions(width_px=3.5))), fresh)
        # cache=False: exact undistortion instead of the tables, the same points to far below 1e-6 mm
        exact = measure_profile(img, CAM, pl, MeasureOptions(StripeOptions(width_px=3.5)), cache=False)
        assert np.array_equal(exact.valid, fresh.valid) and np.array_equal(exact.uv, fresh.uv, equal_nan=True)
        assert np.nanmax(np.abs(exact.points - fresh.points)) < 1e-6
    assert profile_cache_info()["size"] == 1
    # a fully built table gives the same numbers as the lazily filled one
    full = ProfileMeasurer(CAM, pl, MeasureOptions(StripeOptions(width_px=3.5)))
    full.build_lookup()
    assert full.lookup_complete
    for img in frames:
        assert same(full(img), measure_profile(img, CAM, pl, MeasureOptions(StripeOptions(width_px=3.5))))


def test_repeated_calls_do_not_rebuild(frames):
    measure_profile(frames[0], CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    info = profile_cache_info()
    assert (info["misses"], info["hits"], info["size"]) == (1, 0, 1)
    m = next(iter(M._profile_cache.values()))
    built = m.blocks_built
    assert 0 < built < m._built.size  # only the blocks the stripe needs
    for _ in range(3):
        measure_profile(frames[0], CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    assert m.blocks_built == built  # same frame: nothing built again
    assert profile_cache_info()["hits"] == 3
    # an equal camera and plane built anew (by value, not identity) hit the same entry
    measure_profile(frames[0], copy_camera(CAM), LightPlane(PLANE.normal, PLANE.d),
                    MeasureOptions(StripeOptions(width_px=3.5)))
    assert profile_cache_info()["misses"] == 1 and m.blocks_built == built


def test_changed_camera_plane_shape_or_options_miss(frames):
    img = frames[0]
    base = measure_profile(img, CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    # another distortion: other tables, other points
    cam2 = copy_camera(CAM, dist=np.array(CAM.dist) * 1.05)
    p2 = measure_profile(img, cam2, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    assert profile_cache_info()["misses"] == 2
    assert not np.array_equal(p2.points, base.points, equal_nan=True)
    assert same(p2, ProfileMeasurer(cam2, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))(img))
    tabs = [m._xy for m in M._profile_cache.values()]
    assert tabs[0] is not tabs[1]
    blocks = M._profile_cache[next(iter(M._profile_cache))]._built
    assert not np.array_equal(tabs[0][blocks.repeat(32, 0).repeat(64, 1)[: tabs[0].shape[0], : tabs[0].shape[1]]],
                              tabs[1][blocks.repeat(32, 0).repeat(64, 1)[: tabs[1].shape[0], : tabs[1].shape[1]]])
    # another focal length
    cam3 = copy_camera(CAM, K=np.array(CAM.K) * [[1.01], [1.01], [1]])
    assert not np.array_equal(measure_profile(img, cam3, PLANE, MeasureOptions(StripeOptions(width_px=3.5))).points, base.points, equal_nan=True)
    # another plane (offset, then normal): other points, never the stale entry
    pl2 = LightPlane(PLANE.normal, PLANE.d * 1.01)
    q = measure_profile(img, CAM, pl2, MeasureOptions(StripeOptions(width_px=3.5)))
    assert same(q, ProfileMeasurer(CAM, pl2, MeasureOptions(StripeOptions(width_px=3.5)))(img))
    assert not np.array_equal(q.points, base.points, equal_nan=True)
    n3 = PLANE.normal + [0.0, 0.01, 0.0]
    pl3 = LightPlane(n3, PLANE.d)
    assert same(measure_profile(img, CAM, pl3, MeasureOptions(StripeOptions(width_px=3.5))), ProfileMeasurer(CAM, pl3,
                                                                              MeasureOptions(StripeOptions(width_px=3.5)))(img))
    # a covariance added: sigma appears
    s = measure_profile(img, CAM, plane_with_cov(PLANE), MeasureOptions(StripeOptions(width_px=3.5)))
    assert np.all(np.isnan(base.sigma_mm)) and np.isfinite(s.sigma_mm[s.valid]).all()
    # other options, roi, axis: other entries
    r = measure_profile(img, CAM, PLANE,
                        MeasureOptions(StripeOptions(width_px=3.5), roi=(0, 20, CAM.width, CAM.height - 40)))
    assert len(r) == CAM.height - 40
    assert same(r, ProfileMeasurer(CAM, PLANE,
                                   MeasureOptions(StripeOptions(width_px=3.5), roi=(0, 20, CAM.width, CAM.height - 40)))(img))
    assert same(measure_profile(img, CAM, PLANE, MeasureOptions(StripeOptions(width_px=4.0))), ProfileMeasurer(CAM, PLANE,
                                                                                MeasureOptions(StripeOptions(width_px=4.0)))(img))
    # a colour image of the same size: another shape, another entry
    n = profile_cache_info()["misses"]
    measure_profile(np.repeat(img[..., None], 3, axis=2), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    assert profile_cache_info()["misses"] == n + 1
    assert profile_cache_info()["size"] <= M.PROFILE_CACHE_SIZE  # least recently used dropped


def test_bad_input_is_not_cached(frames):
    with pytest.raises(LightplaneError):
        measure_profile(frames[0], CAM, PLANE, MeasureOptions(axis="diagonal"))
    with pytest.raises(LightplaneError):
        measure_profile(frames[0], CAM, PLANE, MeasureOptions(smooth_lines=4))
    with pytest.raises(LightplaneError):
        measure_profile(frames[0][:-1], CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))  # wrong size for the camera
    assert profile_cache_info()["size"] == 0


def test_tables_not_pickled_and_rebuilt_lazily(frames):
    import pickle

    m = ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    a = m(frames[0])
    m2 = pickle.loads(pickle.dumps(m))
    assert not m2.has_lookup and m.has_lookup
    assert same(m2(frames[0]), a)
