"""Speed of the live loop (docs/live.md): profiles per second and latency from exposure to profile at
1280x960, with the work an open page causes.

Run: ``.venv/bin/python benchmarks/bench_live.py [--fps 60] [--seconds 8] [--rounds 3]``.

Frames of the simulated turntable sensor (a sphere on the table, realistic image formation: speckle,
noise, vignetting) are rendered first, then replayed from memory at a fixed rate
(:class:`lightplane.live.sources.ArraySource`, with a camera driver's queue of ``--queue`` frames, default
4: a frame pushed out of the queue before the loop takes it is dropped and counted, never waited for) through :class:`lightplane.live.engine.LiveEngine` with the simulated sensor's
calibration (profiles in mm).  Meanwhile a "page" asks for what the live page shows: the JPEG preview
(640 px wide) at ``--preview-hz``, the status at 2 Hz, and one subscriber turns every profile event into
JSON as a websocket would.  Per round: profiles/s (profiles made / the round's length), latency from the
frame's exposure time to its profile (median, p99), frames dropped; each round at the camera's
``--fps`` and again at ``--capacity-fps`` (a faster camera: how many profiles/s the loop can make).
Beside them, in the same run: one frame's profile measured alone
(:class:`lightplane.measure.profile.ProfileMeasurer`, median of 50), the loop's least possible cost.
Bars: >= 60 profiles/s, no frame dropped at a 60 frames/s camera, median latency <= 30 ms (2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time

import numpy as np

from lightplane.live.engine import LiveEngine
from lightplane.live.simulated import SimulatedSensor
from lightplane.live.sources import REPLAY_QUEUE, ArraySource
from lightplane.measure.profile import ProfileMeasurer
from results import at_least, at_most, figure, record


def render_frames(n: int, seed: int = 0) -> tuple[list[np.ndarray], SimulatedSensor]:
    """``n`` laser frames of the simulated turntable at ``360/n``° apart (1280x960, realistic)."""
    sim = SimulatedSensor("turntable", fps=None, difficulty="realistic", seed=seed)
    frames = []
    for k in range(n):
        img, _ = sim.view(((True,), round(k * 360.0 / n, 9)))
        frames.append(img)
    return frames, sim


class Page:
    """What an open page asks of the engine: previews, status, one subscriber's events as JSON."""

    def __init__(self, engine: LiveEngine, preview_hz: float) -> None:
        self.engine, self.preview_hz = engine, preview_hz
        self.stop = threading.Event()
        self.previews = self.events = self.bytes = 0
        self.q = engine.subscribe()
        self.threads = [threading.Thread(target=self._poll, daemon=True),
                        threading.Thread(target=self._socket, daemon=True)]

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def _poll(self) -> None:
        period, next_status = 1.0 / self.preview_hz, 0.0
        while not self.stop.is_set():
            t = time.monotonic()
            p = self.engine.latest_preview(640)
            if p is not None:
                self.previews += 1
                self.bytes += len(p[0]) + len(json.dumps(p[1]))
            if t >= next_status:
                json.dumps(self.engine.status())
                next_status = t + 0.5
            self.stop.wait(max(0.0, period - (time.monotonic() - t)))

    def _socket(self) -> None:
        while not self.stop.is_set():
            try:
                ev = self.q.get(timeout=0.2)
            except Exception:  # queue.Empty
                continue
            self.bytes += len(json.dumps(ev))
            self.events += 1

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(2.0)
        self.engine.unsubscribe(self.q)


def one_round(frames, sim: SimulatedSensor, fps: float, seconds: float, preview_hz: float,
              queue: int = REPLAY_QUEUE) -> dict:
    eng = LiveEngine(ArraySource(frames, fps=fps, queue=queue), sensor=sim.sensor)
    page = Page(eng, preview_hz)
    eng.start()
    page.start()
    time.sleep(1.0)  # warm-up: the measurer's tables, the first frames
    s0 = eng.status()
    t0 = time.monotonic()
    time.sleep(seconds)
    s1 = eng.status()
    t1 = time.monotonic()
    page.close()
    eng.stop()
    n = s1["frames"] - s0["frames"]
    lat = np.array(list(eng._lat)[-n:]) * 1000.0 if n else np.array([np.nan])  # the round's profiles
    return {"profiles_per_s": n / (t1 - t0), "latency_median_ms": float(np.median(lat)),
            "latency_p99_ms": float(np.percentile(lat, 99)), "dropped": s1["dropped"] - s0["dropped"],
            "frames_offered": int(round((t1 - t0) * fps)), "previews": page.previews, "events": page.events,
            "points": s1["points"]}


def profile_alone(frames, sim: SimulatedSensor, repeat: int = 50) -> float:
    """One frame's profile on its own (ms, median): the loop's least possible cost per frame."""
    eng = LiveEngine(ArraySource(frames), sensor=sim.sensor)
    eng._process(eng.source.read())  # builds the measurer as the loop does (width estimated once)
    m = next(iter(eng._measurers.values()))
    assert isinstance(m, ProfileMeasurer)
    ts = []
    for k in range(repeat):
        t = time.perf_counter()
        m(frames[k % len(frames)])
        ts.append(time.perf_counter() - t)
    return float(np.median(ts) * 1000.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fps", type=float, default=60.0, help="replay rate, frames/s")
    ap.add_argument("--queue", type=int, default=REPLAY_QUEUE,
                    help="frames the replay queues for a late loop, as a camera driver (1: only the newest)")
    ap.add_argument("--seconds", type=float, default=8.0, help="length of a round, s")
    ap.add_argument("--capacity-fps", type=float, default=120.0, help="replay rate of the capacity rounds, frames/s")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--preview-hz", type=float, default=15.0, help="previews the page asks for per second")
    ap.add_argument("--frames", type=int, default=12, help="distinct frames rendered (replayed in a loop)")
    ap.add_argument("--no-record", action="store_true", help="print only, write no results file")
    args = ap.parse_args()
    t = time.perf_counter()
    frames, sim = render_frames(args.frames)
    print(f"rendered {len(frames)} frames {frames[0].shape[1]}x{frames[0].shape[0]} in {time.perf_counter() - t:.1f} s;"
          f" cpus {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}")
    rounds: dict[float, list[dict]] = {args.fps: [], args.capacity_fps: []}
    alone, loads = [], []
    for r in range(args.rounds):
        alone.append(profile_alone(frames, sim))
        for fps, got in rounds.items():
            res = one_round(frames, sim, fps, args.seconds, args.preview_hz, args.queue)
            got.append(res)
            loads.append(os.getloadavg()[0])
            print(f"round {r + 1}: {res['profiles_per_s']:.1f} profiles/s at {fps:g} frames/s offered, latency "
                  f"median {res['latency_median_ms']:.1f} ms, p99 {res['latency_p99_ms']:.1f} ms, dropped "
                  f"{res['dropped']} of {res['frames_offered']}, {res['previews']} previews, {res['events']} events, "
                  f"{res['points']} points per profile; one profile alone {alone[-1]:.1f} ms; "
                  f"load average {os.getloadavg()[0]:.1f}")
    med = {fps: {k: float(np.median([r[k] for r in got])) for k in got[0]} for fps, got in rounds.items()}
    for fps, m in med.items():
        print(f"median of rounds at {fps:g} frames/s: {m['profiles_per_s']:.1f} profiles/s, latency median "
              f"{m['latency_median_ms']:.1f} ms, p99 {m['latency_p99_ms']:.1f} ms, dropped {m['dropped']:.0f} per round")
    if not args.no_record:
        record("bench_live", figures(med[args.fps], med[args.capacity_fps], args, float(np.median(alone)),
                                     float(np.median(loads))))


def figures(cam: dict, cap: dict, args, alone_ms: float, load: float) -> list[dict]:
    ref = ("one profile alone (ProfileMeasurer, median of 50)", alone_ms, "ms")

    def stat(fps: float) -> str:
        return (f"median of {args.rounds} rounds of {args.seconds:g} s at {fps:g} frames/s offered (a queue of "
                f"{args.queue} frame{'s' if args.queue > 1 else ''} for a late loop, as a camera driver's), page open "
                f"(previews at {args.preview_hz:g} Hz, one subscriber); {os.cpu_count()} cores shared with other "
                f"jobs: load average {load:.1f}")

    return [
        figure("live_profiles_per_s", f"live profiles/s, 1280x960, camera at {args.capacity_fps:g} frames/s",
               cap["profiles_per_s"], "1/s", statistic=stat(args.capacity_fps), target=at_least(60.0, "1/s")),
        figure("live_latency_median_ms", f"live latency exposure -> profile, median, {args.fps:g} frames/s",
               cam["latency_median_ms"], "ms", statistic=stat(args.fps), reference=ref, target=at_most(30.0, "ms")),
        figure("live_latency_p99_ms", f"live latency exposure -> profile, p99, {args.fps:g} frames/s",
               cam["latency_p99_ms"], "ms", statistic=stat(args.fps), reference=ref),
        figure("live_dropped_per_round", f"live frames dropped, {args.fps:g} frames/s", cam["dropped"], "frames",
               statistic=stat(args.fps) + f"; of {cam['frames_offered']:.0f} frames per round",
               target=at_most(0, "frames")),
        figure("live_dropped_capacity", f"live frames dropped, {args.capacity_fps:g} frames/s", cap["dropped"],
               "frames", statistic=stat(args.capacity_fps) + f"; of {cap['frames_offered']:.0f} frames per round"),
    ]


if __name__ == "__main__":
    main()
