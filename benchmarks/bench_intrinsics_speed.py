"""Speed of ``calibrate_camera`` on the 30-view calibration capture, optionally against a
reference checkout in the same run.

The capture is ``bench_calibrate.py``'s (15x11 corners of 8 mm, realistic imaging, rendered once and
cached under ``benchmarks/out/renders``; k3 fixed).  Each version runs in its own worker process
(its ``src`` first on ``PYTHONPATH``), which reads the 30 images once and calibrates once to warm up
(numba's compilation or cache load, imports); then the workers calibrate in turn, interleaved, and
each reports the CPU time of its process (``time.process_time``) and the wall time of the call.
Printed: min over ``--repeats`` per version, the ratio of the minima, the camera's error against the
renderer's, and (with a reference) the largest difference between the two versions' corners and
intrinsics.  CPU time, not wall time, because the benchmark machines are shared.

    .venv/bin/python benchmarks/bench_intrinsics_speed.py [--repeats 3] [--reference /path/to/checkout]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
TAG = "@@bench@@ "


def _worker() -> None:  # runs in the worker process: commands on stdin, one JSON line each
    import time

    import cv2

    import lightplane
    from lightplane.camera.model import Camera
    from lightplane.camera.intrinsics import CameraCalibrationOptions, calibrate_camera
    from lightplane.core.io import read_image

    boards = Path(sys.argv[sys.argv.index("--worker") + 1])
    truth = json.loads((boards / "truth.json").read_text())
    imgs = [read_image(boards / v["file"]) for v in truth["views"]]
    ref = Camera.load(boards / "camera.json")
    board = tuple(truth["board"]["inner_corners"])
    print(TAG + json.dumps({"module": str(Path(lightplane.__file__).resolve().parent)}), flush=True)
    for line in sys.stdin:
        cmd = json.loads(line)
        c0, t0 = time.process_time(), time.perf_counter()
        ic = calibrate_camera(imgs, board, truth["board"]["square_mm"],
                              options=CameraCalibrationOptions(flags=cv2.CALIB_FIX_K3))
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
        if cmd.get("save"):
            np.savez(cmd["save"], corners=np.stack(ic.corners_uv), K=ic.camera.K, dist=ic.camera.dist)
        err = {k: float(getattr(ic.camera, k) - getattr(ref, k)) for k in ("fx", "fy", "cx", "cy")}
        print(TAG + json.dumps({"cpu": cpu, "wall": wall, "err": err, "views": len(ic.used),
                                "refit": ic.options.get("lens_frame_refit_corners")}), flush=True)


class _Version:
    def __init__(self, label: str, root: Path, boards: Path) -> None:
        env = dict(os.environ, PYTHONPATH=str(root / "src"))
        self.label = label
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker", str(boards)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=root)
        self.module = self._reply()["module"]
        self.runs: list[dict] = []

    def _reply(self) -> dict:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith(TAG):
                return json.loads(line[len(TAG):])
        raise RuntimeError(f"{self.label}: the worker ended (exit {self.proc.wait()})")

    def run(self, save: str | None = None) -> dict:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"save": save}) + "\n")
        self.proc.stdin.flush()
        return self._reply()

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--boards-seed", type=int, default=1)
    ap.add_argument("--reference", type=Path, help="a checkout of another version (its src/ is imported)")
    args = ap.parse_args()
    sys.path.insert(0, str(HERE))
    from bench_calibrate import _boards

    boards = _boards(args.boards_seed)
    if hasattr(os, "getloadavg"):
        print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs (CPU time per process reported)")
    versions = [_Version("this", HERE.parent, boards)]
    if args.reference is not None:
        versions.append(_Version("reference", args.reference.resolve(), boards))
    with tempfile.TemporaryDirectory() as tmp:
        warm = [v.run(save=str(Path(tmp) / f"{v.label}.npz")) for v in versions]
        for v, w in zip(versions, warm):
            print(f"{v.label:<10} {v.module}: first call {w['wall']:.1f} s wall, {w['cpu']:.1f} s CPU "
                  f"(compilation or cache load included)")
        for _ in range(args.repeats):
            for v in versions:
                v.runs.append(v.run())
        saved = {v.label: np.load(Path(tmp) / f"{v.label}.npz") for v in versions}
    for v in versions:
        v.close()
    print(f"\ncalibrate_camera, {warm[0]['views']} views of {boards.name} (k3 fixed), min of {args.repeats} "
          f"interleaved runs:")
    best = {}
    for v in versions:
        cpu = min(r["cpu"] for r in v.runs)
        wall = min(r["wall"] for r in v.runs)
        best[v.label] = cpu
        e = v.runs[-1]["err"]
        print(f"  {v.label:<10} {cpu:6.2f} s CPU  {wall:6.2f} s wall   error vs the renderer's camera: "
              + "  ".join(f"{k} {e[k]:+.6f}" for k in ("fx", "fy", "cx", "cy"))
              + f" px   (refit corners {v.runs[-1]['refit']})")
    from results import figure, record

    stat = f"min of {args.repeats} runs"
    ref = None
    if args.reference is not None:
        a, b = saved["this"], saved["reference"]
        print(f"  this / reference: {best['this'] / best['reference']:.3f}x the CPU time")
        ref = (f"the same, {args.reference.name}", best["reference"], "s")
    e = versions[0].runs[-1]["err"]
    record("bench_intrinsics_speed", [
        figure("calibrate_camera_cpu", f"calibrate_camera, {warm[0]['views']} views, CPU", best["this"], "s",
               statistic=stat, reference=ref),
        figure("calibrate_camera_wall", f"calibrate_camera, {warm[0]['views']} views, wall",
               min(r["wall"] for r in versions[0].runs), "s", statistic=stat),
        figure("calibrate_camera_cx_error", "calibrate_camera cx error", e["cx"], "px",
               statistic="one calibration against the renderer's camera")])
    if args.reference is not None:
        if a["corners"].shape == b["corners"].shape:
            d = np.abs(a["corners"] - b["corners"])
            print(f"  corners: max |difference| {d.max():.2e} px, RMS {np.sqrt(np.mean(d ** 2)):.2e} px; "
                  f"K: max |difference| {np.abs(a['K'] - b['K']).max():.2e} px")


if __name__ == "__main__":
    if "--worker" in sys.argv:
        _worker()
    else:
        main()
