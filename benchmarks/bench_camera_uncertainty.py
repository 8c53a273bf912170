"""Benchmark: is the predicted point uncertainty honest when the camera is calibrated too?

``--sets`` independent data sets, each: its own 16 rendered chessboard views (9x7 inner
corners, 8 mm squares, realistic imaging, the calibration capture's poses) to calibrate
the camera (``calibrate_camera``, default options: 5 coefficients, saddle-fit corners),
then its own 12 rendered realistic circle images (50 mm target) to calibrate the plane
(``ml``) with that camera, the plane's dependence on the intrinsics propagated
(:func:`lightplane.plane.calibrate.propagate_camera`).  Against the exact truth (the default
camera and plane of the renderer), over the working volume 380–520 mm
(``lightplane.evaluate.shapes.plane_accuracy``): the RMS error of the triangulated points in the
camera frame and after the best rigid alignment (shape), against the predicted RMS sigma
of each (all sources, and the plane-only figure); also the normal angle and the offset
at the optical axis, predicted vs actual.  Honest: predicted / actual within 25 %.
Columns: the intrinsics' covariance by default (the residuals' corner noise times the views'
dispersion, :func:`lightplane.camera.intrinsics.view_dispersion`) and with ``noise="white"`` (the
residuals' alone; same estimates, other predictions); the joint refinement (``--joint-white``:
also with the corners weighted by the residuals' sigma alone); the plane solved with the exact
camera; the shape error split to first order into the plane's own part, the camera's part and
their cross term.  The plane's own covariance includes the images' dispersion
(:func:`lightplane.plane.ml.image_dispersion`, measured beside the camera's share); the columns
"without the images' dispersion" divide it out (same estimates, other predictions), and the
exact camera's plane error is also given as its Mahalanobis² under its own covariance.  Per
set the joint is compared with the two-step estimate, with the fraction of sets in which an
efficient estimator that much better on average is still the worse (``_fraction_worse``).

Renders are cached as compressed .npz under ``--cache`` (default /tmp/lightplane_bench_camera_unc).

    .venv/bin/python benchmarks/bench_camera_uncertainty.py [--sets 20]
    .venv/bin/python benchmarks/bench_camera_uncertainty.py --render-only --sets 20   # fill the cache
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

BOARD = (9, 7)
SQUARE_MM = 8.0
N_BOARDS = 16
N_CIRCLES = 12


def _chessboards(cache: Path, k: int, n: int = N_BOARDS) -> list:
    from dataclasses import replace

    from lightplane.simulate.render import CALIBRATION_CAPTURE, BoardOptions, render_chessboard_dataset, settings_tag

    f = cache / f"boards_{BOARD[0]}x{BOARD[1]}_n{n}_s{1000 + k}_{settings_tag()}.npz"
    if f.exists():
        return list(np.load(f)["images"])
    ds = render_chessboard_dataset(n, 1000 + k, BoardOptions(
        difficulty="realistic", capture=replace(CALIBRATION_CAPTURE, board=BOARD, square_mm=SQUARE_MM)))
    _save(f, ds.images)
    return list(ds.images)


def _circles(cache: Path, k: int, n: int = N_CIRCLES) -> list:
    from lightplane.simulate.render import CircleOptions, render_circle_dataset, settings_tag

    f = cache / f"circles_n{n}_s{2000 + k}_{settings_tag()}.npz"
    if f.exists():
        return list(np.load(f)["images"])
    ds = render_circle_dataset(n, 2000 + k, CircleOptions(difficulty="realistic"))
    _save(f, ds.images)
    return list(ds.images)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", type=int, default=20)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/lightplane_bench_camera_unc"))
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument("--summary", action="store_true", help="only summarise the sets already in out/")
    ap.add_argument("--fresh", action="store_true", help="forget the sets already in out/")
    ap.add_argument("--no-joint", action="store_true", help="without the joint refinement's columns")
    ap.add_argument("--joint-white", action="store_true",
                    help="also the joint with the corners weighted by the residuals' sigma alone")
    ap.add_argument("--name", default="bench_camera_uncertainty", help="name of the result files in out/")
    args = ap.parse_args()
    if args.render_only:
        for k in range(args.first, args.first + args.sets):
            t0 = time.perf_counter()
            _chessboards(args.cache, k)
            _circles(args.cache, k)
            print(f"set {k} rendered in {time.perf_counter() - t0:.0f} s", flush=True)
        return
    run(args)


def _save(f: Path, images) -> None:
    f.parent.mkdir(parents=True, exist_ok=True)
    tmp = f.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, images=np.stack(images))
    tmp.replace(f)


def _errors(cam, plane, cam_true, plane_true, vol, prefix: str = "") -> dict:
    """Actual and predicted errors of (camera, plane) against the truth over ``vol``."""
    from lightplane.plane.triangulate import triangulate
    from lightplane.evaluate.shapes import rigid_align
    from lightplane.plane.uncertainty import volume_sigma

    est = triangulate(cam, plane, vol.uv)
    e = est - vol.points
    ok = np.all(np.isfinite(e), axis=1)
    pred = volume_sigma(cam, plane, vol)
    C = np.asarray(plane.covariance)
    rec = plane.meta.get("camera_jacobian")
    Cc = np.asarray(rec["covariance_camera"]) if rec else np.zeros((4, 4))
    h = np.append(plane_true.point_on_axis(), 1.0)
    out = {
        "frame_mm": float(np.sqrt(np.mean(np.sum(e[ok] ** 2, axis=1)))),
        "shape_mm": rigid_align(est[ok], vol.points[ok]).rms_mm,
        "pred_frame_mm": pred.camera_frame_mm, "pred_shape_mm": pred.shape_mm, "pred_plane_only_mm": pred.plane_only_mm,
        "angle_deg": float(np.degrees(plane.angle_to(plane_true))),
        "offset_mm": float(plane.signed_distance(plane_true.point_on_axis()[None])[0]),
        "pred_angle_deg": float(np.degrees(np.sqrt(np.trace((C + Cc)[:3, :3])))),
        "pred_angle_plane_only_deg": float(np.degrees(np.sqrt(np.trace(C[:3, :3])))),
        "pred_offset_mm": float(np.sqrt(h @ (C + Cc) @ h)), "pred_offset_plane_only_mm": float(np.sqrt(h @ C @ h)),
    }
    if cam.covariance is not None:
        p_true = np.r_[cam_true.fx, cam_true.fy, cam_true.cx, cam_true.cy, cam_true.dist]
        p_est = np.r_[cam.fx, cam.fy, cam.cx, cam.cy, cam.dist]
        out.update({"cx_err_px": float(p_est[2] - p_true[2]), "cy_err_px": float(p_est[3] - p_true[3]),
                    "cx_sigma_px": float(np.sqrt(cam.covariance[2, 2])),
                    "cy_sigma_px": float(np.sqrt(cam.covariance[3, 3])),
                    "intrinsics_mahalanobis2": float((p_est - p_true) @ np.linalg.pinv(cam.covariance)
                                                     @ (p_est - p_true)),
                    "n_free": int(np.sum(np.diag(cam.covariance) > 0))})
        out.update(_shape_from_intrinsics_error(cam, plane, cam_true, vol, p_est - p_true))
    return {prefix + k: v for k, v in out.items()}


def _shape_from_intrinsics_error(cam, plane, cam_true, vol, dK) -> dict:
    """The point errors the intrinsics' *actual* error ``dK`` causes through the recorded
    propagation (first order: the camera columns of the error basis, ``dK`` written in their
    steps), camera frame and shape (RMS, mm): when they match the actual errors' camera part,
    the propagation (ray-plane correlation, rigid-motion projection, volume sampling) is right
    and a low prediction is the intrinsics' error exceeding their covariance."""
    from lightplane.plane.uncertainty import camera_steps, point_error_basis, shape_error_basis

    if not plane.meta.get("camera_jacobian"):
        return {}
    E, inc = point_error_basis(cam, plane, vol.uv)
    steps = camera_steps(cam)
    if not inc or len(steps) == 0:
        return {}
    xi = np.linalg.lstsq(steps.T, dK, rcond=None)[0]
    ok = np.all(np.isfinite(E), axis=(1, 2))
    Ec = E[ok][:, :, 4:]
    d = Ec @ xi
    ds = shape_error_basis(Ec, vol.points[ok]) @ xi
    return {"from_dK_frame_mm": float(np.sqrt(np.mean(np.sum(d**2, axis=1)))),
            "from_dK_shape_mm": float(np.sqrt(np.mean(np.sum(ds**2, axis=1)))),
            "xi_norm2": float(xi @ xi)}


def _corner_truth_error(res, k: int) -> dict:
    """The corners against the renderer's exact ones (its poses re-drawn from its seed), over the
    views used: RMS of the detection error and of the calibration's residuals (px, per
    coordinate), the neighbour correlation of the error along the board's rows, and the
    Mahalanobis² of the intrinsics' change that the detection error alone causes (first order:
    ``δK`` of the Gauss–Newton solve on the errors, board poses marginalised, against the
    covariance the calibration states): white corner noise gives the number of free parameters."""
    import cv2

    from lightplane.simulate.scene import default_camera
    from dataclasses import replace

    from lightplane.simulate.render import CALIBRATION_CAPTURE as CC
    from lightplane.simulate.render import board_corners, sample_board_poses

    cam_true = default_camera()
    poses = sample_board_poses(N_BOARDS, np.random.default_rng(1000 + k), replace(CC, board=BOARD, square_mm=SQUARE_MM),
                               camera=cam_true)
    obj = board_corners(BOARD, SQUARE_MM)
    cam = res.camera
    err, corr = [], []
    P = 4 + cam.dist.size
    S = np.zeros((P, P))
    g = np.zeros(P)
    for name, uv, rv, tv in zip(res.used, res.corners_uv, res.rvecs, res.tvecs):
        R, t = poses[int(name.split()[-1])]
        true = cam_true.project(obj @ R.T + t)
        if np.sum((uv[::-1] - true) ** 2) < np.sum((uv - true) ** 2):  # the board's 180° ambiguity
            true = true[::-1]
        e = uv - true
        err.append(e)
        g3 = e.reshape(BOARD[1], BOARD[0], 2)
        corr.append(np.mean(g3[:, 1:] * g3[:, :-1]))
        _, jac = cv2.projectPoints(obj, rv, tv, cam.K, cam.dist)
        Je, Ji = jac[:, :6], jac[:, 6:6 + P]
        C = Ji.T @ Je
        Bi = np.linalg.inv(Je.T @ Je)
        S += Ji.T @ Ji - C @ Bi @ C.T
        g += Ji.T @ e.ravel() - C @ Bi @ (Je.T @ e.ravel())
    e = np.concatenate(err)
    r = np.concatenate(res.residuals_px)
    sig = res.options["covariance_sigma_px"]
    dK = np.linalg.solve(S, g)
    return {"corner_truth_rms_px": float(np.sqrt(np.mean(e**2))), "corner_residual_rms_px": float(np.sqrt(np.mean(r**2))),
            "corner_truth_neighbour_corr": float(np.mean(corr) / np.mean(e**2)),
            "detector_mahalanobis2": float(dK @ S @ dK / sig**2)}


def _image_dispersion(plane) -> float:
    """The images' dispersion the plane's covariance includes (1.0 when it does not apply it)."""
    nm = plane.meta.get("noise_model") or {}
    return float(nm.get("image_dispersion") or 1.0) if nm.get("image_dispersion_applied") else 1.0


def _scaled_plane(plane, phi: float):
    """The plane with its own covariance (not the camera's share) times ``phi`` (the images' dispersion)."""
    from lightplane.plane.model import LightPlane

    return LightPlane(plane.normal, plane.d, phi * np.asarray(plane.covariance), meta=dict(plane.meta))


def _plane_error_whitened(plane, plane_true) -> list:
    """The plane's error (a, b, c, d) whitened by its own covariance (rank 3: the normal's norm fixed):
    its squared length is the Mahalanobis² (chi² with 3 dof when the covariance is right)."""
    C = np.asarray(plane.covariance)
    sgn = 1.0 if plane.normal @ plane_true.normal > 0 else -1.0
    e = np.r_[plane.normal - sgn * plane_true.normal, plane.d - sgn * plane_true.d]
    w, V = np.linalg.eigh(C)
    keep = w > 1e-12 * w.max()
    return (V[:, keep].T @ e / np.sqrt(w[keep])).tolist()


def _with_white_camera(cam, plane, dispersion: float):
    """The camera and plane with the intrinsics' covariance of independent corner errors (``noise="white"``:
    the default's divided by the views' dispersion; the plane's recorded Jacobian is the same)."""
    from dataclasses import replace

    from lightplane.plane.model import LightPlane

    C = np.asarray(cam.covariance) / dispersion
    cam_w = replace(cam, covariance=C)
    rec = dict(plane.meta["camera_jacobian"])
    J = np.asarray(rec["matrix"])
    rec["covariance_camera"] = (J @ C @ J.T).tolist()
    meta = dict(plane.meta)
    meta["camera_jacobian"] = rec
    return cam_w, LightPlane(plane.normal, plane.d, plane.covariance, meta=meta)


def _undispersed(cam, plane, psi: float):
    """The joint camera and plane with the joint dispersion ``psi`` divided out of every covariance
    (the intrinsics', the plane's own and its camera share): the same estimates, the weights' prediction."""
    cam_w, plane_w = _with_white_camera(cam, plane, psi)
    return cam_w, _scaled_plane(plane_w, 1 / psi)


def _shape_parts(est, est_true_cam, points) -> dict:
    """First-order split of the shape error (the rigid motion over the volume projected out) into the
    exact camera's part (the plane's own errors), the camera's part (the rest) and their cross term
    (mm²; 2 × the mean inner product): the shape² is their sum."""
    from lightplane.plane.uncertainty import rigid_motion_basis

    ok = np.all(np.isfinite(est), axis=1) & np.all(np.isfinite(est_true_cam), axis=1)
    Q = rigid_motion_basis(points[ok])
    def proj(d):
        f = d.ravel()
        return (f - Q @ (Q.T @ f)).reshape(-1, 3)
    a = proj(est_true_cam[ok] - points[ok])
    b = proj(est[ok] - est_true_cam[ok])
    n = len(a)
    return {"lin_shape_own_mm": float(np.sqrt(np.sum(a**2) / n)), "lin_shape_camera_mm": float(np.sqrt(np.sum(b**2) / n)),
            "lin_shape_cross_mm2": float(2 * np.sum(a * b) / n)}


def _hausman(cam, cam_joint) -> dict:
    """Is the joint's shift of the intrinsics what the circles' extra information explains?  Under
    the model the shift's covariance is Cov(two-step) − Cov(joint) (the joint efficient): its
    Mahalanobis² under that (pseudo-inverse), ~chi² with its rank's dof; no truth used."""
    d = np.r_[cam_joint.fx - cam.fx, cam_joint.fy - cam.fy, cam_joint.cx - cam.cx, cam_joint.cy - cam.cy,
              np.asarray(cam_joint.dist) - np.asarray(cam.dist)]
    D = np.asarray(cam.covariance) - np.asarray(cam_joint.covariance)
    w, V = np.linalg.eigh(0.5 * (D + D.T))
    keep = w > 1e-9 * w.max()
    z = V[:, keep].T @ d
    return {"joint_shift_mahalanobis2": float(np.sum(z**2 / w[keep])), "joint_shift_rank": int(keep.sum()),
            "joint_shift_mahalanobis2_two_step_cov": float(d @ np.linalg.pinv(np.asarray(cam.covariance)) @ d)}


def one_set(cache: Path, k: int, joint: bool = True, joint_white: bool = False) -> dict:
    """Calibrate camera and plane from set ``k``; errors against the truth and predicted sigmas,
    two-step and (``joint``) with the joint refinement; and the plane solved with the true camera
    (the plane calibration's own share)."""
    from lightplane.plane.calibrate import PlaneCalibrationOptions, observe_images, solve_observations
    from lightplane.camera.intrinsics import calibrate_camera
    from lightplane.plane.joint import refine_joint
    from lightplane.simulate.scene import default_camera, default_plane
    from lightplane.plane.uncertainty import working_volume_grid

    t0 = time.perf_counter()
    cam_true, plane_true = default_camera(), default_plane()
    res = calibrate_camera(_chessboards(cache, k), BOARD, SQUARE_MM)
    cam = res.camera
    obs = observe_images(_circles(cache, k), cam, 50.0, PlaneCalibrationOptions(workers=2))
    cal = solve_observations(obs, cam, 50.0, "ml")
    vol = working_volume_grid(cam_true, plane_true, distance_mm=(380.0, 520.0))
    disp = float(res.options.get("covariance_dispersion") or 1.0)
    row = {"set": k, "views": len(res.used), "images_used": cal.n_used,
           "corner_sigma_px": res.options["covariance_sigma_px"], "view_dispersion": disp,
           "covariance_noise": res.options.get("covariance_noise")}
    row.update(_corner_truth_error(res, k))
    row.update(_errors(cam, cal.plane, cam_true, plane_true, vol))
    if res.options.get("covariance_noise") == "views":
        # the same, the intrinsics' covariance of independent corner errors (noise="white")
        row.update(_errors(*_with_white_camera(cam, cal.plane, disp), cam_true, plane_true, vol, "white_"))
    phi = _image_dispersion(cal.plane)
    row["image_dispersion"] = phi
    # the same without the images' dispersion (the plane's own covariance as the noise model says)
    row.update(_errors(cam, _scaled_plane(cal.plane, 1 / phi), cam_true, plane_true, vol, "noimgdisp_"))
    t1 = time.perf_counter()
    row["seconds"] = t1 - t0
    # the plane calibration's own share: the same observations solved with the exact camera
    cal_t = solve_observations(obs, cam_true, 50.0, "ml")
    row.update(_errors(cam_true, cal_t.plane, cam_true, plane_true, vol, "truecam_"))
    phi_t = _image_dispersion(cal_t.plane)
    row["truecam_image_dispersion"] = phi_t
    row.update(_errors(cam_true, _scaled_plane(cal_t.plane, 1 / phi_t), cam_true, plane_true, vol,
                       "truecam_noimgdisp_"))
    row["truecam_dx"] = _plane_error_whitened(cal_t.plane, plane_true)
    from lightplane.plane.triangulate import triangulate
    est_t = triangulate(cam_true, cal_t.plane, vol.uv)
    row.update(_shape_parts(triangulate(cam, cal.plane, vol.uv), est_t, vol.points))
    if joint:
        t2 = time.perf_counter()
        jc = refine_joint(res, cal)
        row.update(_errors(jc.camera, jc.plane_cal.plane, cam_true, plane_true, vol, "joint_"))
        row.update({"joint_" + a: b for a, b in
                    _shape_parts(triangulate(jc.camera, jc.plane_cal.plane, vol.uv), est_t, vol.points).items()})
        row["joint_seconds"] = time.perf_counter() - t2
        row.update(_hausman(cam, jc.camera))
        psi = jc.result.dispersion if jc.result.dispersion_applied else 1.0
        row["joint_dispersion"] = jc.result.dispersion
        row.update(_errors(*_undispersed(jc.camera, jc.plane_cal.plane, psi), cam_true, plane_true, vol, "jointnd_"))
        if joint_white and res.options.get("covariance_noise") == "views":
            # the joint with the corners weighted by the residuals' sigma alone (before the views' dispersion)
            from dataclasses import replace

            res_w = replace(res, options={**res.options, "covariance_noise": "white"})
            cam_w, _ = _with_white_camera(cam, cal.plane, disp)
            cal_w = replace(cal, camera=cam_w) if hasattr(cal, "camera") else cal
            jw = refine_joint(replace(res_w, camera=cam_w), cal_w)
            row.update(_errors(jw.camera, jw.plane_cal.plane, cam_true, plane_true, vol, "jointw_"))
        row["joint_cost_drop"] = jc.result.cost_start - jc.result.cost
    return row


QUANTITIES = (("camera frame", "frame_mm", "pred_frame_mm"), ("shape", "shape_mm", "pred_shape_mm"),
              ("camera frame, plane-only sigma", "frame_mm", "pred_plane_only_mm"),
              ("normal angle", "angle_deg", "pred_angle_deg"),
              ("offset at the axis", "offset_mm", "pred_offset_mm"),
              ("offset, plane-only sigma", "offset_mm", "pred_offset_plane_only_mm"))
#: Column sets: two-step, joint refinement, plane solved with the exact camera (the plane's own share).
VARIANTS = (("two-step", ""), ("two-step, white corner noise", "white_"),
            ("two-step, without the images' dispersion", "noimgdisp_"), ("joint", "joint_"),
            ("joint, without the joint dispersion", "jointnd_"), ("joint, white corner noise", "jointw_"), ("true camera", "truecam_"),
            ("true camera, without the images' dispersion", "truecam_noimgdisp_"))


def _fraction_worse(q: float) -> float:
    """How often an estimator whose RMS error is ``q`` times another's is nevertheless the worse of the
    two in one data set, when it is the efficient one (its error uncorrelated with the difference,
    Hausman's lemma) and the errors are one-dimensional Gaussians: ``e₂ = e_J + δ``, ``Var δ = (1/q² − 1)
    Var e_J``; worse when ``δ (2 e_J + δ) < 0``: ``1/2 − arcsin(ρ)/π`` with ``ρ = r / sqrt(4 + r²)``,
    ``r² = 1/q² − 1``.  1/2 for q = 1, 0 only for q = 0."""
    r2 = max(1.0 / max(q, 1e-12) ** 2 - 1.0, 0.0)
    return float(0.5 - np.arcsin(np.sqrt(r2 / (4.0 + r2))) / np.pi)


def summarise(rows: list[dict]) -> dict:
    keys = [k for k in rows[0] if k != "set" and all(k in r and isinstance(r[k], (int, float)) for r in rows)]
    a = {k: np.array([r[k] for r in rows], float) for k in keys}
    rms = {k: float(np.sqrt(np.mean(v**2))) for k, v in a.items()}
    out: dict = {"sets": len(rows)}
    for label, pre in VARIANTS:
        if pre + "frame_mm" not in rms:
            continue
        block = {}
        for name, act, pred in QUANTITIES:
            if pre == "truecam_" and "plane-only" in name:
                continue
            block[name] = {"actual_rms": rms[pre + act], "predicted_rms": rms[pre + pred],
                           "ratio": rms[pre + pred] / rms[pre + act]}
        if pre + "intrinsics_mahalanobis2" in a:
            block["mean_intrinsics_mahalanobis2"] = float(np.mean(a[pre + "intrinsics_mahalanobis2"]))
            block["n_free"] = int(np.max(a[pre + "n_free"]))
            block["cx_err_rms_px"], block["cy_err_rms_px"] = rms[pre + "cx_err_px"], rms[pre + "cy_err_px"]
            block["cx_sigma_rms_px"], block["cy_sigma_rms_px"] = rms[pre + "cx_sigma_px"], rms[pre + "cy_sigma_px"]
        out[label] = block
    if "joint_frame_mm" in a:
        # per set: joint / two-step error (never worse: every ratio <= 1 within the sets' noise)
        for pre in ("joint_", "jointw_"):
            for q in ("frame_mm", "shape_mm", "angle_deg", "offset_mm"):
                if pre + q not in a:
                    continue
                r = np.abs(a[pre + q]) / np.abs(a[q])
                out[f"{pre}over_two_step_{q}"] = {"median": float(np.median(r)), "max": float(np.max(r)),
                                                  "sets_worse": int(np.sum(r > 1.0)),
                                                  "worse_by_max_mm": float(np.max(np.abs(a[pre + q]) - np.abs(a[q]))),
                                                  "rms_ratio": rms[pre + q] / rms[q],
                                                  "expected_fraction_worse": _fraction_worse(rms[pre + q] / rms[q])}
        out["median_joint_seconds"] = float(np.median(a["joint_seconds"]))
    # sampling tolerance of an RMS over n sets of a ~1-dof error: relative sd ~ 1/sqrt(2n)
    out["rms_relative_sd"] = float(1 / np.sqrt(2 * len(rows)))
    out["corner_truth_rms_px"] = rms.get("corner_truth_rms_px")
    out["corner_sigma_rms_px"] = rms.get("corner_sigma_px")
    out["corner_residual_rms_px"] = rms.get("corner_residual_rms_px")
    for pre in ("", "joint_"):
        if pre + "from_dK_shape_mm" in rms:
            out[pre + "from_dK"] = {"frame_mm": rms[pre + "from_dK_frame_mm"], "shape_mm": rms[pre + "from_dK_shape_mm"],
                                    "mean_xi_norm2": float(np.mean(a[pre + "xi_norm2"]))}
    if "truecam_shape_mm" in rms:
        # the actual errors' camera part: what the exact camera removes (in quadrature)
        for q in ("frame_mm", "shape_mm"):
            out["camera_part_actual_" + q] = float(np.sqrt(max(rms[q] ** 2 - rms["truecam_" + q] ** 2, 0.0)))
            out["camera_part_predicted_" + q] = float(np.sqrt(max(rms["pred_" + q] ** 2
                                                                  - rms["truecam_pred_" + q] ** 2, 0.0)))
    for pre in ("", "joint_"):
        if pre + "lin_shape_cross_mm2" in a:
            c = a[pre + "lin_shape_cross_mm2"]
            out[pre + "shape_parts"] = {"own_mm": rms[pre + "lin_shape_own_mm"],
                                        "camera_mm": rms[pre + "lin_shape_camera_mm"],
                                        "mean_cross_mm2": float(np.mean(c)),
                                        "cross_sd_of_mean_mm2": float(np.std(c, ddof=1) / np.sqrt(len(c))),
                                        "sets_cross_positive": int(np.sum(c > 0))}
    if "view_dispersion" in a:
        out["mean_view_dispersion"] = float(np.mean(a["view_dispersion"]))
    if "joint_dispersion" in a:
        v = a["joint_dispersion"]
        out["joint_dispersion"] = {"mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)),
                                   "min": float(np.min(v)), "max": float(np.max(v))}
    for pre in ("", "truecam_"):
        if pre + "image_dispersion" in a:
            v = a[pre + "image_dispersion"]
            out[pre + "image_dispersion"] = {"mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)),
                                             "min": float(np.min(v)), "max": float(np.max(v))}
    if all("truecam_dx" in r for r in rows):
        # the exact camera's plane error, Mahalanobis² under its own covariance (chi², 3 dof, if right)
        m2 = np.array([np.sum(np.square(r["truecam_dx"])) for r in rows])
        phi = a.get("truecam_image_dispersion", np.ones(len(rows)))
        out["truecam_mahalanobis2"] = {"mean": float(np.mean(m2)), "median": float(np.median(m2)),
                                       "mean_without_dispersion": float(np.mean(m2 * phi)),
                                       "median_without_dispersion": float(np.median(m2 * phi)),
                                       "largest": float(np.max(m2)), "set_of_largest": int(rows[int(np.argmax(m2))]["set"])}
    out["mean_corner_truth_neighbour_corr"] = float(np.mean(a["corner_truth_neighbour_corr"]))
    out["mean_detector_mahalanobis2"] = float(np.mean(a["detector_mahalanobis2"]))
    out["median_seconds_per_set"] = float(np.median(a["seconds"]))
    return out


def run(args) -> None:
    out_dir = Path(__file__).resolve().parent / "out"
    out_dir.mkdir(exist_ok=True)
    log = out_dir / f"{args.name}.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() and not args.fresh else []
    done = {r["set"] for r in rows}
    if not args.summary:
        for k in range(args.first, args.first + args.sets):
            if k in done:
                continue
            r = one_set(args.cache, k, joint=not args.no_joint, joint_white=args.joint_white)
            rows.append(r)
            with log.open("a") as f:
                f.write(json.dumps(r) + "\n")
            print(f"set {k}: camera frame {r['frame_mm']:.4f} mm (predicted {r['pred_frame_mm']:.4f}), shape "
                  f"{r['shape_mm']:.4f} mm (predicted {r['pred_shape_mm']:.4f}); joint: camera frame "
                  f"{r.get('joint_frame_mm', np.nan):.4f} mm (predicted {r.get('joint_pred_frame_mm', np.nan):.4f}), "
                  f"shape {r.get('joint_shape_mm', np.nan):.4f} mm (predicted "
                  f"{r.get('joint_pred_shape_mm', np.nan):.4f}); {r['seconds']:.0f} s + joint "
                  f"{r.get('joint_seconds', np.nan):.0f} s", flush=True)
    s = summarise(rows)
    print(f"\n{s['sets']} independent sets (each: {N_BOARDS} chessboard views {BOARD[0]}x{BOARD[1]}, "
          f"{N_CIRCLES} circle images, realistic renders), working volume 380-520 mm")
    for label, _ in VARIANTS:
        if label not in s:
            continue
        print(f"\n{label}:")
        print(f"{'quantity':<32} {'actual RMS':>11} {'predicted':>10} {'pred/act':>8}")
        for name, _a, _p in QUANTITIES:
            if name not in s[label]:
                continue
            v = s[label][name]
            unit = "deg" if "angle" in name else "mm"
            print(f"{name:<32} {v['actual_rms']:>8.4f} {unit:<3}{v['predicted_rms']:>9.4f} {v['ratio']:>8.2f}")
        if "mean_intrinsics_mahalanobis2" in s[label]:
            b = s[label]
            print(f"principal point error RMS cx {b['cx_err_rms_px']:.3f} px, cy {b['cy_err_rms_px']:.3f} px "
                  f"(sigma RMS {b['cx_sigma_rms_px']:.3f}, {b['cy_sigma_rms_px']:.3f} px); mean Mahalanobis² of "
                  f"the intrinsics' error {b['mean_intrinsics_mahalanobis2']:.1f} ({b['n_free']} expected)")
    for pre in ("joint_", "jointw_"):
        for q in ("frame_mm", "shape_mm", "angle_deg", "offset_mm"):
            key = f"{pre}over_two_step_{q}"
            if key in s:
                v = s[key]
                print(f"{pre[:-1]} / two-step |error| per set, {q}: median {v['median']:.2f}, max {v['max']:.2f}, "
                      f"{v['sets_worse']} of {s['sets']} sets worse (by up to {v['worse_by_max_mm']:.4f} "
                      f"{q.split('_')[-1]}); ratio of the RMS {v['rms_ratio']:.2f} (an efficient estimator that "
                      f"much better on average is still worse in {100 * v['expected_fraction_worse']:.0f} % "
                      f"of the sets: {v['expected_fraction_worse'] * s['sets']:.1f} of {s['sets']})")
    print(f"corners against the exact ones: RMS {s['corner_truth_rms_px']:.4f} px per coordinate; residual-based "
          f"sigma {s['corner_sigma_rms_px']:.4f} px (residual RMS {s['corner_residual_rms_px']:.4f} px); neighbour "
          f"correlation {s['mean_corner_truth_neighbour_corr']:.2f}; mean Mahalanobis² of the intrinsics' change "
          f"the detection errors alone cause (first order) {s['mean_detector_mahalanobis2']:.1f}")
    if "camera_part_actual_shape_mm" in s:
        print(f"camera's part (total minus the exact camera's, in quadrature): camera frame actual "
              f"{s['camera_part_actual_frame_mm']:.4f} mm, predicted {s['camera_part_predicted_frame_mm']:.4f} mm; "
              f"shape actual {s['camera_part_actual_shape_mm']:.4f} mm, predicted "
              f"{s['camera_part_predicted_shape_mm']:.4f} mm")
    for pre, label in (("", "two-step"), ("joint_", "joint")):
        if pre + "shape_parts" in s:
            v = s[pre + "shape_parts"]
            print(f"{label} shape error, first order over the volume: the plane's own (exact camera) {v['own_mm']:.4f} mm, "
                  f"the camera's part {v['camera_mm']:.4f} mm RMS, cross term {v['mean_cross_mm2'] * 1e6:+.1f} "
                  f"± {v['cross_sd_of_mean_mm2'] * 1e6:.1f} µm² per set (mean ± its sd; positive in "
                  f"{v['sets_cross_positive']} of {s['sets']} sets)")
    if "mean_view_dispersion" in s:
        print(f"views' dispersion of the corner noise along the intrinsics (mean over the sets): "
              f"{s['mean_view_dispersion']:.2f}")
    if "joint_dispersion" in s:
        v = s["joint_dispersion"]
        print(f"joint dispersion (the views' and images' pulls on the intrinsics and the plane): mean {v['mean']:.2f}, "
              f"sd {v['sd']:.2f} (range {v['min']:.2f}-{v['max']:.2f}) over the sets")
    for pre, label in (("", "two-step"), ("truecam_", "exact camera")):
        if pre + "image_dispersion" in s:
            v = s[pre + "image_dispersion"]
            print(f"images' dispersion of the plane ({label}): mean {v['mean']:.2f}, sd {v['sd']:.2f} "
                  f"(range {v['min']:.2f}-{v['max']:.2f}) over the sets")
    if "truecam_mahalanobis2" in s:
        v = s["truecam_mahalanobis2"]
        print(f"exact camera, the plane's error in its own covariance: Mahalanobis² mean {v['mean']:.2f} (median "
              f"{v['median']:.2f}; chi² with 3 dof: mean 3, median 2.37); without the images' dispersion mean "
              f"{v['mean_without_dispersion']:.2f} (median {v['median_without_dispersion']:.2f}); largest "
              f"{v['largest']:.1f} (set {v['set_of_largest']})")
    if "from_dK" in s:
        v = s["from_dK"]
        print(f"errors the intrinsics' actual error causes through the propagation: camera frame {v['frame_mm']:.4f} mm, "
              f"shape {v['shape_mm']:.4f} mm (|dK|² in sigma units, mean {v['mean_xi_norm2']:.1f})")
    print(f"sampling sd of an RMS over {s['sets']} sets: ~{100 * s['rms_relative_sd']:.0f} %")
    (out_dir / f"{args.name}.json").write_text(json.dumps({"summary": s, "rows": rows}, indent=1))
    from results import between, figure, record

    figs = []
    for label, pre in (("two-step", "two_step"), ("joint", "joint")):
        for name, q in (("camera frame", "frame"), ("shape", "shape")):
            if label in s and name in s[label]:
                v = s[label][name]
                figs.append(figure(f"{pre}_{q}_predicted", f"{label}: predicted {name} point sigma", v["predicted_rms"],
                                   "mm", statistic=f"RMS over {s['sets']} sets, 380-520 mm",
                                   reference=(f"actual {name} error", v["actual_rms"], "mm"),
                                   target=between(0.75, 1.25, "x", of="ratio")))
    record(args.name, figs)


if __name__ == "__main__":
    main()
