"""Timing of the cross-ratio evaluation and Zhou's method on rendered 1280x960 chessboards.

Run: ``.venv/bin/python benchmarks/bench_evaluate.py``.  Prints medians (ms) and the
ratio to the target.  Target (ours, not the paper's): a whole image — board pose
and on-board stripe — in under 500 ms, so a hand-held check keeps up with capture;
the geometry after it (cross-ratio, distances, plane fit) in under 5 ms per image.
"""

from __future__ import annotations

import time

import numpy as np

from lightplane import LightPlane
from lightplane.plane.zhou import board_views_and_stripes, plane_from_board_stripes
from lightplane.evaluate.crossratio import evaluate_views
from lightplane.simulate.render import BoardOptions, render_chessboard_dataset
from results import at_most, figure, record

TARGET_IMAGE_MS = 500.0
TARGET_GEOMETRY_MS = 5.0


def median_ms(fn, repeat: int) -> float:
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(t))


def main() -> None:
    n = 4
    ds = render_chessboard_dataset(n, 1, BoardOptions(with_stripe=True, laser_off=True, samples=4, edge_samples=8))
    on = [im for im, nm in zip(ds.images, ds.names) if "_off" not in nm]
    off = [im for im, nm in zip(ds.images, ds.names) if "_off" in nm]
    truth = LightPlane.from_dict(ds.truth["plane"])
    sq = ds.truth["board"]["square_mm"]
    kw = dict(board=(9, 6), square_mm=sq)
    board_views_and_stripes(on[:1], ds.camera, **kw, background_images=off[:1])  # warm-up (numba, OpenCV)
    t_img = median_ms(lambda: board_views_and_stripes(on, ds.camera, **kw, background_images=off), 3) / n
    t_raw = median_ms(lambda: board_views_and_stripes(on, ds.camera, **kw), 3) / n
    poses, stripes, _ = board_views_and_stripes(on, ds.camera, **kw, background_images=off)
    t_geo = median_ms(lambda: evaluate_views(ds.camera, [truth], poses, stripes, **kw), 20) / n
    t_zhou = median_ms(lambda: plane_from_board_stripes(ds.camera, poses, stripes), 20) / n
    print(f"board pose + stripe, laser-off frame given : {t_img:8.1f} ms/image  ({t_img / TARGET_IMAGE_MS:.2f} x target "
          f"{TARGET_IMAGE_MS:.0f} ms)")
    print(f"board pose + stripe, no laser-off frame    : {t_raw:8.1f} ms/image  ({t_raw / TARGET_IMAGE_MS:.2f} x target)")
    print(f"cross-ratio points + distances, one plane  : {t_geo:8.2f} ms/image  ({t_geo / TARGET_GEOMETRY_MS:.2f} x target "
          f"{TARGET_GEOMETRY_MS:.0f} ms)")
    print(f"Zhou plane fit (+ jackknife)               : {t_zhou:8.2f} ms/image  ({t_zhou / TARGET_GEOMETRY_MS:.2f} x target)")
    s3, s20 = f"median of 3 runs / {n} images", f"median of 20 runs / {n} images"
    record("bench_evaluate", [
        figure("board_pose_stripe_laser_off", "board pose + stripe, laser-off frame given", t_img, "ms",
               statistic=s3, target=at_most(TARGET_IMAGE_MS, "ms")),
        figure("board_pose_stripe", "board pose + stripe, no laser-off frame", t_raw, "ms",
               statistic=s3, target=at_most(TARGET_IMAGE_MS, "ms")),
        figure("cross_ratio_geometry", "cross-ratio points + distances", t_geo, "ms",
               statistic=s20, target=at_most(TARGET_GEOMETRY_MS, "ms")),
        figure("zhou_plane_fit", "Zhou plane fit + jackknife", t_zhou, "ms",
               statistic=s20, target=at_most(TARGET_GEOMETRY_MS, "ms"))])


if __name__ == "__main__":
    main()
