"""lightplane.core.geometry: one family per primitive (exact, noisy, degenerate input, bad shapes)."""
import numpy as np
import pytest

from lightplane.core import geometry as g


def _ellipse_conic(cx, cy, a, b, th):
    c, s = np.cos(th), np.sin(th)
    R = np.array([[c, -s], [s, c]])
    Q = R @ np.diag([1 / a**2, 1 / b**2]) @ R.T
    m = np.array([cx, cy])
    C = np.zeros((3, 3))
    C[:2, :2] = Q
    C[:2, 2] = C[2, :2] = -Q @ m
    C[2, 2] = m @ Q @ m - 1.0
    return C / np.linalg.norm(C)


def _ellipse_points(cx, cy, a, b, th, n=200):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    c, s = np.cos(th), np.sin(th)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.column_stack([cx + c * x - s * y, cy + s * x + c * y])


# ------------------------------------------------------------------ Failure
def test_failure_is_falsy_with_reason():
    f = g.Failure("the points are collinear")
    assert not f
    assert f.reason == "the points are collinear"


# ------------------------------------------------------------------ robust_sigma
class TestRobustSigma:
    def test_exact(self):
        x = np.array([-1.0, 0.0, 1.0])
        assert g.robust_sigma(x) == pytest.approx(1.4826)
        assert g.robust_sigma(x + 100.0) == pytest.approx(1.4826)
        assert g.robust_sigma(np.array([1.0, 2.0, 9.0]), center=False) == pytest.approx(2 * 1.4826)

    def test_noisy_matches_sigma_and_ignores_outliers(self):
        rng = np.random.default_rng(0)
        x = rng.normal(5.0, 2.0, 20000)
        x[:1000] = 1e6  # 5 % gross outliers
        assert g.robust_sigma(x) == pytest.approx(2.0, rel=0.1)
        assert g.robust_sigma(rng.normal(0, 0.3, 20000), center=False) == pytest.approx(0.3, rel=0.03)

    def test_matches_scipy_within_the_constant(self):
        scipy_stats = pytest.importorskip("scipy.stats")
        x = np.random.default_rng(1).normal(size=101)
        ref = scipy_stats.median_abs_deviation(x, scale="normal")
        assert g.robust_sigma(x) == pytest.approx(ref, rel=1e-5)

    def test_upper_median(self):
        x = np.array([-4.0, 1.0, 2.0, 3.0])  # |x| sorted 1 2 3 4: upper middle 3, median 2.5
        assert g.robust_sigma(x, center=False, upper_median=True) == pytest.approx(3 * 1.4826)
        assert g.robust_sigma(x, center=False) == pytest.approx(2.5 * 1.4826)
        odd = np.array([3.0, -1.0, 2.0])
        assert g.robust_sigma(odd, center=False, upper_median=True) == g.robust_sigma(odd, center=False)
        with pytest.raises(ValueError):
            g.robust_sigma(x, upper_median=True)

    def test_degenerate(self):
        assert g.robust_sigma(np.full(7, 3.0)) == 0.0
        assert np.isnan(g.robust_sigma(np.array([])))
        assert np.isnan(g.robust_sigma(np.array([1.0, np.nan, 2.0])))

    def test_shapes(self):
        x = np.arange(12.0).reshape(3, 4)
        assert g.robust_sigma(x) == g.robust_sigma(x.ravel())
        assert isinstance(g.robust_sigma([1.0, 2.0, 4.0]), float)


# ------------------------------------------------------------------ tls_line
class TestTlsLine:
    def test_exact(self):
        t = np.linspace(-5, 5, 11)
        d0 = np.array([3.0, 4.0]) / 5
        p = np.array([1.0, 2.0]) + t[:, None] * d0
        m, d, n = g.tls_line(p)
        np.testing.assert_allclose(m, [1.0, 2.0], atol=1e-12)
        assert abs(abs(d @ d0) - 1) < 1e-12
        assert abs(d @ n) < 1e-12 and abs(np.linalg.norm(n) - 1) < 1e-12
        np.testing.assert_allclose((p - m) @ n, 0, atol=1e-12)

    def test_noisy(self):
        rng = np.random.default_rng(2)
        t = rng.uniform(-100, 100, 2000)
        sigma = 0.5
        p = np.column_stack([t, 0.2 * t + 3]) + rng.normal(0, sigma, (2000, 2))
        m, d, n = g.tls_line(p)
        true_d = np.array([1.0, 0.2]) / np.hypot(1, 0.2)
        # direction error ~ sigma / (spread sqrt(N)): spread ~ 58 px
        assert np.degrees(np.arccos(min(1.0, abs(d @ true_d)))) < 5 * np.degrees(sigma / (58 * np.sqrt(2000)))
        assert np.std((p - m) @ n) == pytest.approx(sigma, rel=0.1)

    def test_degenerate(self):
        m, d, n = g.tls_line(np.ones((4, 2)))  # coincident points: any unit pair
        np.testing.assert_allclose(m, [1, 1])
        assert abs(np.linalg.norm(d) - 1) < 1e-12 and abs(d @ n) < 1e-12

    @pytest.mark.parametrize("shape", [(5, 3), (5,), (1, 2), (0, 2)])
    def test_bad_shapes(self, shape):
        with pytest.raises(ValueError):
            g.tls_line(np.zeros(shape))


# ------------------------------------------------------------------ robust_line
class TestRobustLine:
    def test_exact(self):
        t = np.linspace(0, 100, 50)
        p = np.column_stack([t, 0.5 * t + 7])
        m, d, n, inl = g.robust_line(p, rel_tol=1e-9)
        assert inl.all()
        np.testing.assert_allclose((p - m) @ n, 0, atol=1e-9)

    @pytest.mark.parametrize("center", [False, True])
    def test_noisy_with_outliers(self, center):
        rng = np.random.default_rng(8)
        t = rng.uniform(-200, 200, 600)
        sigma = 0.3
        p = np.column_stack([t, -0.3 * t + 50]) + rng.normal(0, sigma, (600, 2))
        out = rng.random(600) < 0.15
        # outliers on both sides: with center=True the threshold is still about the line, so
        # one-sided outliers that shift the first fit are the caller's concern
        p[out, 1] += rng.uniform(10, 80, out.sum()) * rng.choice([-1, 1], out.sum())
        m, d, n, inl = g.robust_line(p, center=center, refits=10)
        assert not np.any(inl & out)
        assert inl[~out].mean() > 0.99  # 4 sigma keeps nearly all the good points
        assert np.std((p[inl] - m) @ n) == pytest.approx(sigma, rel=0.1)
        true_n = np.array([0.3, 1.0]) / np.hypot(0.3, 1.0)
        assert abs(abs(n @ true_n) - 1) < 1e-5

    def test_min_tol_and_min_points(self):
        p = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.4]])
        assert g.robust_line(p, min_tol=1.0)[3].all()
        # rejection down to fewer than min_points is not adopted
        inl = g.robust_line(p[:3] + [[0, 0], [0, 0], [0, 5.0]], min_points=3)[3]
        assert inl.all()

    def test_degenerate(self):
        p = np.array([[0.0, 0.0], [1.0, 1.0], [np.nan, 2.0], [3.0, 3.0]])
        m, d, n, inl = g.robust_line(p)
        assert not inl[2] and inl[[0, 1, 3]].all()
        assert abs(abs(d @ [2**-0.5, 2**-0.5]) - 1) < 1e-12
        with pytest.raises(ValueError):
            g.robust_line(np.array([[0.0, 0.0], [np.nan, 1.0]]))

    @pytest.mark.parametrize("shape", [(5, 3), (5,)])
    def test_bad_shapes(self, shape):
        with pytest.raises(ValueError):
            g.robust_line(np.zeros(shape))


# ------------------------------------------------------------------ fit_plane_tls
class TestFitPlane:
    def test_exact(self):
        rng = np.random.default_rng(3)
        n0 = np.array([1.0, -2.0, 2.0]) / 3
        u = np.cross(n0, [1, 0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(n0, u)
        ab = rng.uniform(-50, 50, (30, 2))
        p = 400 * n0 + ab[:, :1] * u + ab[:, 1:] * v
        n, d, lam = g.fit_plane_tls(p)
        assert abs(abs(n @ n0) - 1) < 1e-12
        np.testing.assert_allclose(p @ n + d, 0, atol=1e-9)
        assert lam < 1e-12

    def test_noisy_and_weights(self):
        rng = np.random.default_rng(4)
        p = np.column_stack([rng.uniform(-50, 50, (3000, 2)), 300 + rng.normal(0, 0.1, 3000)])
        n, d, lam = g.fit_plane_tls(p)
        assert abs(abs(n[2]) - 1) < 1e-4
        assert abs(abs(d) - 300) < 0.02
        assert lam / len(p) == pytest.approx(0.01, rel=0.1)  # sum of squared distances
        w = np.ones(len(p))
        n2, d2, lam2 = g.fit_plane_tls(p, 2 * w)
        np.testing.assert_allclose(n2, n, atol=1e-12)
        assert lam2 == pytest.approx(2 * lam)

    def test_degenerate(self):
        p = np.column_stack([np.arange(5.0), np.zeros(5), np.zeros(5)])  # collinear: a zero eigenvalue
        n, d, lam = g.fit_plane_tls(p)
        assert abs(n[0]) < 1e-12 and lam == 0.0

    @pytest.mark.parametrize("shape", [(5, 2), (5,), (2, 3)])
    def test_bad_shapes(self, shape):
        with pytest.raises(ValueError):
            g.fit_plane_tls(np.zeros(shape))

    def test_scatter(self):
        rng = np.random.default_rng(10)
        p = rng.normal(size=(50, 3)) * [10.0, 3.0, 0.1]
        c, lam, V = g.plane_scatter(p)
        np.testing.assert_allclose(c, p.mean(axis=0))
        assert np.all(np.diff(lam) > 0)
        np.testing.assert_allclose(V.T @ V, np.eye(3), atol=1e-12)
        n, d, lam0 = g.fit_plane_tls(p)
        np.testing.assert_array_equal(n, V[:, 0])
        assert lam0 == pytest.approx(lam[0])
        with pytest.raises(ValueError):
            g.plane_scatter(np.zeros((4, 2)))


# ------------------------------------------------------------------ ray_plane
class TestRayPlane:
    def test_exact(self):
        n = np.array([0.0, 0.6, 0.8])
        c = np.array([10.0, -5.0, 500.0])
        xy = np.array([[0.0, 0.0], [0.1, -0.05], [-0.2, 0.1]])
        P = g.ray_plane(xy, n, c)
        np.testing.assert_allclose((P - c) @ n, 0, atol=1e-9)
        np.testing.assert_allclose(P[:, :2] / P[:, 2:], xy, atol=1e-12)

    def test_noisy_direction_sensitivity(self):
        # a ray error of e (normalised) moves the point by about z * e along the plane
        n, c = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 400.0])
        rng = np.random.default_rng(5)
        e = rng.normal(0, 1e-4, (500, 2))
        P = g.ray_plane(e, n, c)
        assert np.std(P[:, 0]) == pytest.approx(0.04, rel=0.15)

    def test_degenerate(self):
        n, c = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 100.0])  # plane x = 0 holds the optical axis
        P = g.ray_plane(np.array([[0.0, 0.0], [0.1, 0.0], [-0.1, 0.0]]), n, c)
        assert np.all(np.isnan(P[0]))  # parallel ray
        assert np.all(np.isnan(P[1])) and np.all(np.isnan(P[2]))  # meets it at the camera / behind

    def test_behind_camera(self):
        P = g.ray_plane(np.zeros((1, 2)), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -50.0]))
        assert np.all(np.isnan(P))

    def test_bad_shapes(self):
        with pytest.raises(ValueError):
            g.ray_plane(np.zeros((3, 3)), np.array([0.0, 0.0, 1.0]), np.zeros(3))


# ------------------------------------------------------------------ sampson_distance
class TestSampson:
    E = (320.0, 240.0, 120.0, 70.0, 0.4)

    def test_exact(self):
        C = _ellipse_conic(*self.E)
        np.testing.assert_allclose(g.sampson_distance(C, _ellipse_points(*self.E)), 0, atol=1e-9)

    def test_noisy_near_the_curve(self):
        # points moved by delta along the normal: the Sampson distance is delta to first order
        C = _ellipse_conic(*self.E)
        p = _ellipse_points(*self.E, n=400)
        grad = (np.column_stack([p, np.ones(len(p))]) @ C)[:, :2]
        nrm = grad / np.linalg.norm(grad, axis=1, keepdims=True)
        delta = np.random.default_rng(6).normal(0, 0.3, len(p))
        d = g.sampson_distance(C, p + delta[:, None] * nrm)
        # second order: delta² times the largest curvature a / b²
        assert np.all(np.abs(d - delta) <= delta**2 * 120.0 / 70.0**2 + 1e-9)
        assert np.max(np.abs(d - delta)) < 0.02
        np.testing.assert_allclose(g.sampson_distance(C, p + delta[:, None] * nrm, signed=False), np.abs(d))

    def test_sign_convention(self):
        C = _ellipse_conic(*self.E)
        if C[0, 0] + C[1, 1] < 0:
            C = -C
        assert g.sampson_distance(C, np.array([[320.0 + 60.0, 240.0]]))[0] != 0
        inside = g.sampson_distance(C, np.array([[320.0, 240.0 + 1.0]]))[0]
        outside = g.sampson_distance(C, np.array([[1000.0, 1000.0]]))[0]
        assert inside < 0 < outside

    def test_degenerate(self):
        C = _ellipse_conic(*self.E)
        d = g.sampson_distance(C, np.array([[320.0, 240.0]]))  # the centre: zero gradient
        assert np.isfinite(d).all() and abs(d[0]) > 1e6  # huge, not inf
        assert g.sampson_distance(C, np.zeros((0, 2))).shape == (0,)

    def test_bad_shapes(self):
        C = _ellipse_conic(*self.E)
        with pytest.raises(ValueError):
            g.sampson_distance(C, np.zeros((4, 3)))
        with pytest.raises(ValueError):
            g.sampson_distance(np.eye(2), np.zeros((4, 2)))


# ------------------------------------------------------------------ fit_conic
class TestFitConic:
    E = (640.0, 480.0, 150.0, 60.0, 0.3)

    def test_exact(self):
        C = g.fit_conic(_ellipse_points(*self.E, n=50))
        ref = _ellipse_conic(*self.E)
        ref = ref if ref[0, 0] + ref[1, 1] > 0 else -ref
        np.testing.assert_allclose(C, ref, atol=1e-9)
        assert abs(np.linalg.norm(C) - 1) < 1e-12 and C[0, 0] + C[1, 1] > 0

    def test_noisy(self):
        rng = np.random.default_rng(7)
        sigma = 0.5
        p = _ellipse_points(*self.E, n=500) + rng.normal(0, sigma, (500, 2))
        C = g.fit_conic(p)
        d = g.sampson_distance(C, p)
        assert np.sqrt(np.mean(d**2)) == pytest.approx(sigma, rel=0.1)
        # centre of the fit: -A⁻¹ b, within a few sigma / sqrt(N) of the truth
        ctr = -np.linalg.solve(C[:2, :2], C[:2, 2])
        assert np.hypot(*(ctr - self.E[:2])) < 10 * sigma / np.sqrt(500)

    def test_weights(self):
        p = _ellipse_points(*self.E, n=60)
        np.testing.assert_allclose(g.fit_conic(p, np.full(60, 3.0)), g.fit_conic(p), atol=1e-12)
        bad = np.vstack([p, [[0.0, 0.0], [5.0, 900.0]]])  # two outliers with zero weight
        np.testing.assert_allclose(g.fit_conic(bad, np.r_[np.ones(60), 0.0, 0.0]), g.fit_conic(p), atol=1e-9)

    def test_batch_matches_single(self):
        sets = [_ellipse_points(*self.E, n=40), np.zeros((3, 2)), _ellipse_points(100, 50, 20, 10, 1.0, n=30)]
        conics, problems = g.fit_conics(sets)
        assert problems[0] is None and problems[2] is None and "at least 5" in problems[1]
        np.testing.assert_allclose(conics[0], g.fit_conic(sets[0]), atol=1e-15)
        assert np.all(np.isnan(conics[1]))

    @pytest.mark.parametrize("pts, why", [
        (np.zeros((4, 2)), "at least 5"),
        (np.column_stack([np.arange(20.0), 2 * np.arange(20.0)]), "collinear"),
        (np.full((10, 2), 3.0), "coincide"),
        (np.array([[0, 0], [1, 1], [2, 2], [np.nan, 0], [4, 1], [5, 0.0]]), "NaN"),
    ])
    def test_degenerate_is_a_failure_with_its_reason(self, pts, why):
        r = g.fit_conic(pts)
        assert isinstance(r, g.Failure) and not r
        assert why in r.reason

    def test_bad_shapes(self):
        with pytest.raises(ValueError):
            g.fit_conic(np.zeros((10, 3)))
        with pytest.raises(ValueError):
            g.fit_conic(_ellipse_points(*self.E, n=20), np.ones(19))

    def test_the_other_fits_use_it(self):
        from lightplane.plane.circle_pose import fit_rim_conic
        from lightplane.ellipse import fit_ellipse_direct
        from lightplane.core.errors import LightplaneError

        p = _ellipse_points(*self.E, n=30)
        np.testing.assert_array_equal(fit_rim_conic(p), g.fit_conic(p))
        np.testing.assert_array_equal(fit_ellipse_direct(p), g.fit_conic(p))
        r = fit_ellipse_direct(np.zeros((4, 2)))
        assert isinstance(r, g.Failure) and "at least 5" in r.reason
        with pytest.raises(LightplaneError, match="rim: need at least 5"):
            fit_rim_conic(np.zeros((4, 2)), name="rim")


# ------------------------------------------------------------------ default_workers
def test_default_workers():
    import os

    n = g.default_workers()
    assert isinstance(n, int) and n >= 1
    assert n == len(os.sched_getaffinity(0))
