"""Speed of the live loop with the live page really open (docs/live-page.md): profiles per second and
latency from exposure to profile at 1280x960 while ``lightplane live``'s server runs in the same process
and a headless Chromium shows the page (previews about 10 a second, profiles over the websocket 20 a
second, the status twice a second, the page drawing them), or, without Chromium, a client process that
asks for the same (``--client ws``).

Run: ``.venv/bin/python benchmarks/bench_live_page.py [--fps 60] [--seconds 8] [--rounds 3]``.

The frames are bench_live.py's (the simulated turntable, realistic image formation, pre-rendered and
replayed from memory at a fixed rate; a frame the loop is not ready for is dropped and counted).  Each
round runs the engine three times, interleaved: without any page (the reference) and with the served page
open at ``--fps``, and with the page open at ``--capacity-fps`` (a faster camera: how many profiles/s the
loop makes with the page open); same frames, same minute.  The replay queues ``--queue`` frames for a late
loop (default 4, a V4L2 capture's buffers; 1: only the newest frame waits, every hiccup of a frame period
drops one).  Bars: >= 60 profiles/s with the page open (the capacity rounds), no frame dropped at a 60
frames/s camera with the page open, median latency <= 30 ms (2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lightplane.live.engine import LiveEngine
from lightplane.live.server import ServerOptions, listen, serve_in_thread, url_of
from lightplane.live.sources import REPLAY_QUEUE, ArraySource
from bench_live import render_frames
from results import at_least, at_most, figure, record

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "live"))
from _chromium import Chromium, find_chromium  # noqa: E402

#: what the "ws" client does: the page's requests, from its own process
WS_CLIENT = r"""
import json, sys, threading, time, urllib.request
from websockets.sync.client import connect
url, seconds = sys.argv[1], float(sys.argv[2])
stop = time.monotonic() + seconds
counts = {"previews": 0, "profiles": 0}
def previews():
    while time.monotonic() < stop:
        t = time.monotonic()
        with urllib.request.urlopen(url + "api/preview?max_width=650") as r:
            json.load(r)
        counts["previews"] += 1
        time.sleep(max(0.0, 0.08 - (time.monotonic() - t)) + 0.02)
th = threading.Thread(target=previews); th.start()
with connect(url.replace("http", "ws") + "api/ws", max_size=None) as ws:
    while time.monotonic() < stop:
        m = json.loads(ws.recv(timeout=5))
        counts["profiles"] += m.get("type") == "profile"
th.join()
print(json.dumps(counts))
"""


class OpenPage:
    """The page open on a served engine: Chromium, or the "ws" client process."""

    def __init__(self, url: str, client: str, seconds: float, profile_dir: Path) -> None:
        self.client, self.url = client, url
        self.browser = self.proc = None
        if client == "chromium":
            self.browser = Chromium(find_chromium(), profile_dir, size=(1400, 1500))
            self.browser.open(url)
            self.browser.wait_for("window.lpState && lpState.previews >= 2 && lpState.profiles >= 2", 60,
                                  "the page's first previews and profiles")
        else:
            self.proc = subprocess.Popen([sys.executable, "-c", WS_CLIENT, url, str(seconds + 3)],
                                         stdout=subprocess.PIPE, text=True)

    def counts(self) -> dict:
        if self.browser is not None:
            return self.browser.js("({previews: lpState.previews, profiles: lpState.profiles})")
        out, _ = self.proc.communicate(timeout=60)
        return json.loads(out)

    def close(self) -> None:
        if self.browser is not None:
            self.browser.close()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()


def one_round(frames, sim, fps: float, seconds: float, page: str | None, tmp: Path, queue: int = REPLAY_QUEUE) -> dict:
    eng = LiveEngine(ArraySource(frames, fps=fps, queue=queue), sensor=sim.sensor)
    eng.start()
    stop_server, opened = None, None
    try:
        if page is not None:
            sock = listen("127.0.0.1", 0)
            stop_server = serve_in_thread(eng, sock, ServerOptions(output_dir=tmp / "out"))
            opened = OpenPage(url_of(sock), page, seconds, Path(tempfile.mkdtemp(dir=tmp)))
        time.sleep(1.0)  # warm-up
        c0 = opened.counts() if opened is not None and page == "chromium" else {"previews": 0, "profiles": 0}
        s0, t0 = eng.status(), time.monotonic()
        time.sleep(seconds)
        s1, t1 = eng.status(), time.monotonic()
        c1 = opened.counts() if opened is not None else {"previews": 0, "profiles": 0}
    finally:
        if opened is not None:
            opened.close()
        if stop_server is not None:
            stop_server()
        eng.stop()
    n = s1["frames"] - s0["frames"]
    lat = np.array(list(eng._lat)[-n:]) * 1000.0 if n else np.array([np.nan])  # the round's profiles
    return {"profiles_per_s": n / (t1 - t0), "latency_median_ms": float(np.median(lat)),
            "latency_p99_ms": float(np.percentile(lat, 99)), "dropped": s1["dropped"] - s0["dropped"],
            "frames_offered": int(round((t1 - t0) * fps)),
            "page_previews_per_s": (c1["previews"] - c0["previews"]) / (t1 - t0),
            "page_profiles_per_s": (c1["profiles"] - c0["profiles"]) / (t1 - t0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fps", type=float, default=60.0, help="replay rate, frames/s")
    ap.add_argument("--queue", type=int, default=REPLAY_QUEUE,
                    help="frames the replay queues for a late loop, as a camera driver (1: only the newest)")
    ap.add_argument("--capacity-fps", type=float, default=120.0,
                    help="replay rate of the capacity rounds (page open, a faster camera), frames/s")
    ap.add_argument("--seconds", type=float, default=8.0, help="length of a round, s")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=12, help="distinct frames rendered (replayed in a loop)")
    ap.add_argument("--client", choices=("chromium", "ws"), default=None,
                    help="what opens the page (default: chromium when installed, else ws)")
    ap.add_argument("--no-record", action="store_true", help="print only, write no results file")
    args = ap.parse_args()
    client = args.client or ("chromium" if find_chromium() else "ws")
    t = time.perf_counter()
    frames, sim = render_frames(args.frames)
    print(f"rendered {len(frames)} frames {frames[0].shape[1]}x{frames[0].shape[0]} in {time.perf_counter() - t:.1f} s;"
          f" cpus {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}; page opened by {client}")
    got: dict[str, list[dict]] = {"none": [], "page": [], "capacity": []}
    loads = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for mode in ("none", "page", "capacity"):
                fps = args.capacity_fps if mode == "capacity" else args.fps
                res = one_round(frames, sim, fps, args.seconds, None if mode == "none" else client, Path(tmp),
                                args.queue)
                got[mode].append(res)
                loads.append(os.getloadavg()[0])
                print(f"round {r + 1}, {'no page  ' if mode == 'none' else 'page open'}: "
                      f"{res['profiles_per_s']:.1f} profiles/s at {fps:g} frames/s offered, latency median "
                      f"{res['latency_median_ms']:.1f} ms, p99 {res['latency_p99_ms']:.1f} ms, dropped "
                      f"{res['dropped']} of {res['frames_offered']}; the page drew "
                      f"{res['page_previews_per_s']:.1f} previews/s, {res['page_profiles_per_s']:.1f} profiles/s; "
                      f"load average {loads[-1]:.1f}")
    med = {mode: {k: float(np.median([r[k] for r in rs])) for k in rs[0]} for mode, rs in got.items()}
    for mode, m in med.items():
        print(f"median of rounds, {mode}: {m['profiles_per_s']:.1f} profiles/s, latency median "
              f"{m['latency_median_ms']:.1f} ms, p99 {m['latency_p99_ms']:.1f} ms, dropped {m['dropped']:.0f} per round")
    if not args.no_record:
        record("bench_live_page", figures(med, args, client, float(np.median(loads))))


def figures(med: dict, args, client: str, load: float) -> list[dict]:
    page, ref, cap = med["page"], med["none"], med["capacity"]
    stat_cap = (f"median of {args.rounds} rounds of {args.seconds:g} s at {args.capacity_fps:g} frames/s offered "
                f"(how many profiles/s the loop makes with the page open: {cap['dropped']:.0f} of "
                f"{cap['frames_offered']:.0f} frames per round dropped, latency median "
                f"{cap['latency_median_ms']:.1f} ms), the page open in {client}; {os.cpu_count()} cores, "
                f"load average {load:.1f}")
    stat = (f"median of {args.rounds} rounds of {args.seconds:g} s at {args.fps:g} frames/s offered (a queue of "
            f"{args.queue} frame{'s' if args.queue > 1 else ''} for a late loop, as a camera driver's), the page "
            f"served from the engine's process and open in {client} ({page['page_previews_per_s']:.1f} previews/s, "
            f"{page['page_profiles_per_s']:.1f} profiles/s drawn), interleaved with rounds without a page; "
            f"{os.cpu_count()} cores shared with other jobs: load average {load:.1f}")
    return [
        figure("live_page_profiles_per_s",
               f"live profiles/s with the page open, 1280x960, camera at {args.capacity_fps:g} frames/s",
               cap["profiles_per_s"], "1/s", statistic=stat_cap,
               reference=(f"page open, camera at {args.fps:g} frames/s", page["profiles_per_s"], "1/s"),
               target=at_least(60.0, "1/s")),
        figure("live_page_latency_median_ms", "live latency exposure -> profile with the page open, median",
               page["latency_median_ms"], "ms", statistic=stat,
               reference=("no page open", ref["latency_median_ms"], "ms"), target=at_most(30.0, "ms")),
        figure("live_page_latency_p99_ms", "live latency exposure -> profile with the page open, p99",
               page["latency_p99_ms"], "ms", statistic=stat,
               reference=("no page open", ref["latency_p99_ms"], "ms")),
        figure("live_page_dropped_per_round", f"live frames dropped with the page open, {args.fps:g} frames/s",
               page["dropped"], "frames", statistic=stat + f"; of {page['frames_offered']:.0f} frames per round",
               target=at_most(0, "frames")),
    ]


if __name__ == "__main__":
    main()
