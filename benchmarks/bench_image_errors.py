"""Benchmark: where the plane's error with the exact camera exceeds its noise model.

On the circle images of ``bench_camera_uncertainty.py``'s sets (its cache; rendered here when
missing), observed and solved (``ml``) with the exact camera: the points' actual errors are their
residuals at the TRUE plane and poses (the renderer's placements, re-drawn from the set's seed).
Per image they are split into what the noise model (rim and stripe sigmas, autocorrelation times
along the curves) says about the components a fit absorbs and cannot show in its residuals:

- the rim's harmonics 0–2 of the angle (its own pose absorbs them) against harmonics 3–6;
- the stripe's offset and slope along the chord (removed before its autocorrelation is estimated);

each coefficient squared over its model variance ``σ² τ (BᵀB)⁻¹`` (1 on average when the model
holds; sd of a mean over N images ~ sqrt(2/N)).  Per set: the plane's error in the tangent
coordinates of the truth, its Mahalanobis² under the covariance without and with the images'
dispersion (chi², 3 dof, when right), the images' dispersion from the residuals, and the same
statistic at the truth (each image's pull on the plane from its actual errors, summed over the
images without the cross terms, over its expectation 3): what the dispersion estimates.

    .venv/bin/python benchmarks/bench_image_errors.py [--sets 12]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _observations(cache: Path, k: int, cam, observe_images) -> list:
    """The circle images' observations with the exact camera, cached (pickled records) next to the renders."""
    import pickle

    from bench_camera_uncertainty import _circles

    from lightplane.plane.calibrate import ImageObservation, PlaneCalibrationOptions
    from lightplane.simulate.render import settings_tag

    f = cache / f"obs_truecam_s{2000 + k}_{settings_tag()}.pkl"
    if f.exists():
        return [ImageObservation.from_record(r) for r in pickle.loads(f.read_bytes())]
    obs = observe_images(_circles(cache, k), cam, 50.0, PlaneCalibrationOptions(workers=1))
    f.write_bytes(pickle.dumps([o.to_record() for o in obs]))
    return obs


def one_set(cache: Path, k: int) -> dict:
    from lightplane.plane.calibrate import observe_images, solve_observations
    from lightplane.plane.ml import _add_normals, _huber_weights, _Pose, _Problem
    from lightplane.simulate.scene import PlacementOptions, default_camera, default_plane, sample_placements

    cam, pl = default_camera(), default_plane()
    obs = _observations(cache, k, cam, observe_images)
    cal = solve_observations(obs, cam, 50.0, "ml")
    nm = cal.plane.meta["noise_model"]
    used = [o for o in cal.images if o.used]
    rims = [np.asarray(o.rim_uv, float) for o in used]
    sts = [np.asarray(o.stripe_uv, float)[np.asarray(o.placement.stripe_inliers, bool)] for o in used]
    truth = sample_placements(12, np.random.default_rng(2000 + k), PlacementOptions(diameter_mm=50.0), camera=cam, plane=pl)
    tp = []
    for o in used:
        c = o.placement.pose.center
        t = truth[int(np.argmin([np.linalg.norm(q.center - c) for q in truth]))]
        tp.append(_Pose(t.center, t.normal))
    s_r, s_s, t_r, t_s = nm["sigma_rim_px"], nm["sigma_stripe_px"], nm["tau_rim"], nm["tau_stripe"]
    # the ML's weights (its sigmas, autocorrelation times and Huber factors at its estimate)
    est = _Problem(cam, 25.0, rims, sts, cal.plane, [o.placement.pose for o in used])
    is_rim = np.arange(est.m) < est.m_rim
    s_rows = np.where(is_rim, s_r, s_s)
    hub = _huber_weights(est.residuals(est.x0) / s_rows, 3.0)
    row_w = np.sqrt(hub) / (s_rows * np.sqrt(np.where(is_rim, t_r, t_s)))
    # at the truth: the points' actual errors, the linear error of the plane and its split per image
    prob = _Problem(cam, 25.0, rims, sts, pl, tp)
    e = prob.residuals(prob.x0)
    prob.set_row_weights(row_w)
    rw, Jb = prob.evaluate(prob.x0)
    H = _add_normals(*prob.group_normals(rw, Jb))
    Hinv = H.inverse()
    J = prob.dense_jacobian(prob.x0)
    C = Hinv[:3, :3]  # the plane's covariance under the noise model (tangent coordinates of the truth)
    L = np.linalg.cholesky(np.linalg.inv(C))
    img = np.concatenate([prob.rim_idx, prob.st_idx])
    per_img = np.array([L.T @ (Hinv[:3] @ (J[img == i].T @ rw[img == i])) for i in range(prob.n)])
    # the estimate's error in the same coordinates (the estimate's plane in the truth's tangent basis)
    n_est = cal.plane.normal if cal.plane.normal @ pl.normal > 0 else -cal.plane.normal
    d_est = cal.plane.d if cal.plane.normal @ pl.normal > 0 else -cal.plane.d
    dn = n_est / (n_est @ pl.normal) - pl.normal
    dx = np.r_[prob.nt @ dn, d_est - pl.d]
    m2 = float(np.sum((L.T @ dx) ** 2))
    phi = float(nm["image_dispersion"])
    # per image: the components the fit absorbs, against the model
    zr, zr_hi, zs = [], [], []
    er, es_all = e[:prob.m_rim], e[prob.m_rim:]
    for i in range(prob.n):
        xy = rims[i]
        th = np.arctan2(*(xy - xy.mean(0)).T[::-1])
        B = np.column_stack([np.ones(len(th))] + [f(m * th) for m in range(1, 7) for f in (np.cos, np.sin)])
        coef = np.linalg.lstsq(B, er[prob.rim_idx == i], rcond=None)[0]
        z = coef**2 / (s_r**2 * t_r * np.diag(np.linalg.inv(B.T @ B)))
        zr.append(z[:5])
        zr_hi.append(z[5:])
        es = es_all[prob.st_idx == i][prob.st_order[i]]
        Bs = np.column_stack([np.ones(len(es)), np.linspace(-1.0, 1.0, len(es))])
        cs = np.linalg.lstsq(Bs, es, rcond=None)[0]
        zs.append(cs**2 / (s_s**2 * t_s * np.diag(np.linalg.inv(Bs.T @ Bs))))
    return {"set": k, "images": prob.n, "mahalanobis2_model": m2, "mahalanobis2": m2 / phi, "image_dispersion": phi,
            "truth_per_image": float(np.sum(per_img**2) / 3), "rim_harmonics_0_2": np.mean(zr, axis=0).tolist(),
            "rim_harmonics_3_6": np.mean(zr_hi, axis=0).tolist(), "stripe_offset_slope": np.mean(zs, axis=0).tolist(),
            "n": len(zr)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", type=int, default=12)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/lightplane_bench_camera_unc"))
    args = ap.parse_args()
    out = Path(__file__).resolve().parent / "out"
    out.mkdir(exist_ok=True)
    log = out / "bench_image_errors.jsonl"
    rows = [json.loads(x) for x in log.read_text().splitlines()] if log.exists() else []
    done = {r["set"] for r in rows}
    for k in range(args.sets):
        if k in done:
            continue
        r = one_set(args.cache, k)
        rows.append(r)
        with log.open("a") as f:
            f.write(json.dumps(r) + "\n")
        print(f"set {k}: Mahalanobis² {r['mahalanobis2_model']:.2f} (noise model), {r['mahalanobis2']:.2f} (with the "
              f"images' dispersion {r['image_dispersion']:.2f}); at the truth, per image: {r['truth_per_image']:.2f}",
              flush=True)
    w = np.array([r["n"] for r in rows], float)

    def avg(key):
        return np.average(np.array([r[key] for r in rows]), axis=0, weights=w)

    m_mod = np.array([r["mahalanobis2_model"] for r in rows])
    m_d = np.array([r["mahalanobis2"] for r in rows])
    phi = np.array([r["image_dispersion"] for r in rows])
    tpi = np.array([r["truth_per_image"] for r in rows])
    n_img = int(w.sum())
    print(f"\n{len(rows)} sets, {n_img} images (exact camera); a mean of z² over {n_img} images has sd "
          f"~{np.sqrt(2 / n_img):.2f}")
    print("per image, actual over modelled variance (1 when the noise model holds):")
    print("  rim harmonics 0, cos 1, sin 1, cos 2, sin 2 (absorbed by the pose): "
          + ", ".join(f"{x:.2f}" for x in avg("rim_harmonics_0_2")))
    print("  rim harmonics 3-6 (cos, sin; seen by the residuals): " + ", ".join(f"{x:.2f}" for x in avg("rim_harmonics_3_6")))
    print("  stripe offset, slope (removed before tau): " + ", ".join(f"{x:.2f}" for x in avg("stripe_offset_slope")))
    print(f"the images' pull on the plane at the truth over the model's (no cross terms): mean {tpi.mean():.2f}; "
          f"the images' dispersion from the residuals: mean {phi.mean():.2f}, sd {phi.std(ddof=1):.2f}")
    print(f"the plane's Mahalanobis² (chi², 3 dof: mean 3, median 2.37): noise model mean {m_mod.mean():.2f} "
          f"(median {np.median(m_mod):.2f}), with the images' dispersion mean {m_d.mean():.2f} (median "
          f"{np.median(m_d):.2f}); largest {m_mod.max():.1f} (set {rows[int(np.argmax(m_mod))]['set']})")
    print(f"sigma ratio (predicted / actual, RMS over the sets in Mahalanobis units): noise model "
          f"{np.sqrt(3 / m_mod.mean()):.2f}, with the dispersion {np.sqrt(3 * np.mean(phi) / np.mean(m_mod)):.2f}")
    from results import figure, record

    stat = f"{len(rows)} sets, {n_img} images, exact camera"
    record("bench_image_errors", [
        figure("plane_mahalanobis2_model", "plane error's Mahalanobis², noise model", m_mod.mean(), "",
               statistic=f"mean over {len(rows)} sets (chi², 3 dof: 3)"),
        figure("sigma_ratio_model", "plane sigma predicted / actual, noise model", np.sqrt(3 / m_mod.mean()), "x",
               statistic=stat),
        figure("sigma_ratio_dispersion", "plane sigma predicted / actual, with dispersion",
               np.sqrt(3 * np.mean(phi) / np.mean(m_mod)), "x", statistic=stat)])


if __name__ == "__main__":
    main()
