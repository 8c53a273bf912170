"""`lightplane measure-batch` / lightplane.measure.batch on a LocalCluster of 2 worker processes.

Same points as the single-process `measure` (bitwise), whatever the chunking; a worker
killed mid-run loses and duplicates nothing; a re-run writes only the missing
partitions; bad scans fail alone.  A few rendered frames keep this short.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from lightplane import Camera, LightPlane  # noqa: E402
from lightplane.measure.batch import measure_batch, read_manifest, read_points  # noqa: E402
from lightplane.core.errors import LightplaneError  # noqa: E402
from lightplane.measure.scan import Motion, measure_scan, open_frames  # noqa: E402
from lightplane.simulate.render import render_scan_dataset  # noqa: E402
from lightplane.measure.batch import BatchOptions  # noqa: E402

N_FRAMES = 5
STEP = 1.5


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch")
    ds = render_scan_dataset("sphere", n_frames=N_FRAMES, step_mm=STEP, seed=2)
    ds.save(d / "s1")
    LightPlane.from_dict(ds.truth["plane"]).save(d / "plane.json")
    import cv2

    h, w = ds.images[0].shape[:2]
    video = cv2.VideoWriter(str(d / "s3.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h), isColor=False)
    for img in ds.images:
        video.write(img)
    video.release()
    (d / "manifest.csv").write_text(
        "id,input,camera,plane,step,direction,positions\n"
        f"s1,s1,s1/camera.json,plane.json,{STEP},-1;0;0,\n"
        "s2,s1/*.png,s1/camera.json,plane.json,,,\n"
        f"s3,s3.avi,s1/camera.json,plane.json,{STEP},-1;0;0,\n")
    return d


@pytest.fixture(scope="module")
def reference(data, tmp_path_factory):
    """The single-process, threaded `measure` path (2 threads), as NPY records."""
    out = tmp_path_factory.mktemp("ref")
    cam, pl = Camera.load(data / "s1" / "camera.json"), LightPlane.load(data / "plane.json")
    ref = {}
    for sid, motion, src in (("s1", Motion.linear(STEP, (-1, 0, 0)), "s1"), ("s2", Motion.none(), "s1"),
                             ("s3", Motion.linear(STEP, (-1, 0, 0)), "s3.avi")):
        measure_scan(open_frames([data / src]), cam, pl, out / f"{sid}.npy", motion=motion, workers=2,
                     executor="thread")
        ref[sid] = np.load(out / f"{sid}.npy")
    return ref


def same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_identical_to_measure_whatever_the_chunking(data, client, reference, tmp_path):
    import pyarrow.dataset as pds

    # s4: the frames of s2 named by an fsspec URL (file:// here; s3://, gs://... alike), read by the workers
    manifest = data / "manifest-url.csv"
    manifest.write_text((data / "manifest.csv").read_text()
                        + f"s4,{(data / 's1').as_uri()},s1/camera.json,plane.json,,,\n")
    reference = {**reference, "s4": reference["s2"]}
    for chunk in (2, 5):
        out = tmp_path / f"c{chunk}"
        r = measure_batch(manifest, out, batch=BatchOptions(chunk_frames=chunk), client=client)
        assert not r.failed, r.failed
        n_parts = -(-N_FRAMES // chunk)
        for sid in ("s1", "s2", "s3", "s4"):
            assert same(read_points(out, sid), reference[sid]), (chunk, sid)
            parts = sorted(p.name for p in (out / "points" / f"scan={sid}").iterdir())
            assert parts == [f"part-{k}.parquet" for k in range(n_parts if sid != "s3" else 1)]  # a video: one
        assert r.partitions_written == 3 * n_parts + 1 and r.partitions_reused == 0
        assert r.n_frames == 4 * N_FRAMES
    # one hive-partitioned dataset, measure's CSV columns
    t = pds.dataset(out / "points", format="parquet", partitioning="hive").to_table()
    assert t.num_rows == sum(a.size for a in reference.values())
    assert set(t.column_names) == {"x", "y", "z", "frame", "intensity", "sigma_mm", "u", "v", "scan"}
    import json

    m = json.loads((out / "manifest.json").read_text())
    assert m["summary"]["ok"] == 4 and m["provenance"]["versions"]["lightplane"]
    assert [p["frames"] for p in m["scans"][0]["partitions"]] == [[0, N_FRAMES]]


def test_resume_rewrites_only_the_missing_partition(data, client, reference, tmp_path):
    out = tmp_path / "out"
    measure_batch(data / "manifest.csv", out, batch=BatchOptions(chunk_frames=2), client=client)
    folder = out / "points" / "scan=s1"
    (folder / "part-1.parquet").unlink()
    before = {p: p.stat().st_mtime_ns for p in out.glob("points/*/part-*.parquet")}
    r = measure_batch(data / "manifest.csv", out, batch=BatchOptions(chunk_frames=2), client=client)
    assert r.partitions_written == 1 and r.partitions_reused == 6
    after = {p: p.stat().st_mtime_ns for p in out.glob("points/*/part-*.parquet")}
    assert set(after) == set(before) | {folder / "part-1.parquet"}
    assert all(after[p] == t for p, t in before.items())  # the others were not touched
    assert same(read_points(out, "s1"), reference["s1"]) and same(read_points(out, "s2"), reference["s2"])
    # another chunking: nothing stale is kept
    r = measure_batch(data / "manifest.csv", out, batch=BatchOptions(chunk_frames=3), client=client)
    assert r.partitions_written == 4 and r.partitions_reused == 1  # the video's one partition is still valid
    assert same(read_points(out, "s1"), reference["s1"])
    assert sorted(p.name for p in folder.iterdir()) == ["part-0.parquet", "part-1.parquet"]


def test_bad_scans_fail_alone_and_are_reported(data, client, tmp_path):
    import json

    frames = tmp_path / "frames"
    shutil.copytree(data / "s1", frames)
    (frames / sorted(p.name for p in frames.glob("*.png"))[2]).write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    shutil.copy(data / "plane.json", tmp_path / "plane.json")
    (tmp_path / "m.csv").write_text(
        "id,input,camera,plane\n"
        "good,frames,frames/camera.json,plane.json\n"
        "gone,no-such-folder,frames/camera.json,plane.json\n"
        "nocam,frames,missing.json,plane.json\n"
        "small,frames,small.json,plane.json\n"
        f"url,{frames.as_uri()},frames/camera.json,plane.json\n")
    cam = json.loads((frames / "camera.json").read_text())
    cam["width"], cam["height"] = 640, 480  # not the frames' size: that scan fails, as measure refuses it
    (tmp_path / "small.json").write_text(json.dumps(cam))
    addr = client.scheduler.address
    cmd = [sys.executable, "-m", "lightplane", "measure-batch", str(tmp_path / "m.csv"), "-o", str(tmp_path / "o"),
           "--scheduler", addr, "--chunk-frames", "2", "--ply"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "2 of 5 scans measured" in r.stdout
    assert "scan gone" in r.stderr and "scan nocam" in r.stderr and "unreadable frame" in r.stderr
    assert "scan small" in r.stderr

    m = json.loads((tmp_path / "o" / "manifest.json").read_text())
    good = m["scans"][0]
    assert good["status"] == "ok" and good["n_frames"] == N_FRAMES and len(good["skipped"]) == 1
    assert good["skipped"][0][0] == 2 and "truncated" in good["skipped"][0][2]
    assert [s["status"] for s in m["scans"]] == ["ok", "failed", "failed", "failed", "ok"]
    assert m["scans"][4]["skipped"][0][0] == 2 and "truncated" in m["scans"][4]["skipped"][0][2]  # via fsspec
    assert "1280x960" in m["scans"][3]["error"] or "size" in m["scans"][3]["error"], m["scans"][3]["error"]
    assert (tmp_path / "o" / "ply" / "good.ply").is_file()
    # nothing measurable: exit 2, one error line at the end
    (tmp_path / "bad.csv").write_text("id,input,camera,plane\ngone,no-such-folder,frames/camera.json,plane.json\n")
    cmd[4], cmd[6], cmd[7], cmd[8] = str(tmp_path / "bad.csv"), str(tmp_path / "o2"), "--local-workers", "1"
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)  # the command's own LocalCluster
    assert r.returncode == 2 and "no scan could be measured" in r.stderr.splitlines()[-1]
    assert "Dask dashboard" in r.stdout


def test_manifest_errors(tmp_path):
    bad = {"no header": "s1,a,b,c\n", "dup": "id,input,camera,plane\na,x,y,z\na,x,y,z\n",
           "unknown": "id,input,camera,plane,speed\na,x,y,z,1\n", "id": "id,input,camera,plane\n../a,x,y,z\n"}
    for name, text in bad.items():
        (tmp_path / "m.csv").write_text(text)
        with pytest.raises(LightplaneError):
            read_manifest(tmp_path / "m.csv")
    (tmp_path / "m.csv").write_text("id,input,camera,plane,direction\na,x,y,z,1;0;0\n")
    s = read_manifest(tmp_path / "m.csv")[0]
    assert s.input == str(tmp_path / "x") and s.direction == "1;0;0"


def test_worker_killed_mid_run_loses_and_duplicates_nothing(data, client, reference, tmp_path):
    from distributed.diagnostics.plugin import WorkerPlugin

    class KillFirstChunk(WorkerPlugin):
        """The first worker to start a chunk task exits at once (only once, cluster-wide: a marker file).

        Defined here so that it is pickled by value (the workers cannot import this module)."""

        name = "kill-first-chunk"

        def __init__(self, marker: str) -> None:
            self.marker = marker

        def transition(self, key, start, finish, **kwargs) -> None:
            if finish == "executing" and str(key).startswith("chunk-"):
                try:
                    fd = os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                except FileExistsError:
                    return
                os.write(fd, str(key).encode())
                os.close(fd)
                os._exit(1)

    plugin = KillFirstChunk(str(tmp_path / "killed"))
    stale = tmp_path / "out" / "points" / "scan=s1" / ".part-0.parquet.x1y2z3.parquet"  # as a worker killed mid-write leaves
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"PAR1 half a file")
    client.register_plugin(plugin, name=plugin.name)
    try:
        r = measure_batch(data / "manifest.csv", tmp_path / "out", batch=BatchOptions(chunk_frames=1), client=client)
    finally:
        client.unregister_worker_plugin(plugin.name)
    assert (tmp_path / "killed").is_file(), "no worker was killed"
    assert not r.failed and r.partitions_written == 2 * N_FRAMES + 1
    assert not list((tmp_path / "out").glob("points/*/.part-*"))  # no temporary file left
    for sid in ("s1", "s2", "s3"):
        got = read_points(tmp_path / "out", sid)
        assert same(got, reference[sid])
        assert np.array_equal(np.unique(got["frame"]), np.arange(N_FRAMES))


def test_dropped_points_counted_per_scan_and_frame(data, client, tmp_path):
    """A frame without a stripe gives no points, and the manifest counts it as measure does (per reason, per
    frame); the command line prints the totals."""
    import json

    import cv2

    from tests._cli import lightplane

    src = tmp_path / "s"
    shutil.copytree(data / "s1", src)
    frames = sorted(src.glob("*.png"))
    img = cv2.imread(str(frames[2]), cv2.IMREAD_UNCHANGED)
    short = np.full_like(img, int(np.median(img)))
    short[:, :, None][100:110, :] = img[:, :, None][100:110, :]  # a stripe 10 lines long is no stripe
    short[:, :, None][:, 100:110] = img[:, :, None][:, 100:110]
    cv2.imwrite(str(frames[2]), short)
    manifest = tmp_path / "m.csv"
    manifest.write_text("id,input,camera,plane,step,direction,positions\n"
                        f"d,{src},{src / 'camera.json'},{data / 'plane.json'},{STEP},-1;0;0,\n")
    cam, pl = Camera.load(src / "camera.json"), LightPlane.load(data / "plane.json")
    ref = measure_scan(open_frames([src]), cam, pl, tmp_path / "ref.npy", motion=Motion.linear(STEP, (-1, 0, 0)),
                       workers=1, executor="thread")
    assert ref.dropped.frames_without_stripe == 1
    r = measure_batch(manifest, tmp_path / "out", batch=BatchOptions(chunk_frames=2), client=client)
    assert not r.failed, r.failed
    e = json.loads((tmp_path / "out" / "manifest.json").read_text())["scans"][0]
    assert e["dropped"] == ref.dropped.totals and e["frames_without_stripe"] == 1
    assert [f[0] for f in e["frames_dropped"]] == [i for i, _, _ in ref.dropped.frames]
    assert same(read_points(tmp_path / "out", "d"), np.load(tmp_path / "ref.npy"))
    cli = lightplane("measure-batch", manifest, "-o", tmp_path / "out2", "--local-workers", "1")
    assert cli.returncode == 0, cli.stderr
    assert "scan d: dropped: 1 frames without a stripe" in cli.stdout
