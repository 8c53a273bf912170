"""`measure-batch` never leaves a dataset that mixes two runs while its manifest says ok.

One run at a time per output folder (the lock: a second run refused, a dead holder's lock
taken over, another host's broken only when asked); manifest.json says "in progress" until
the run's end; a partition made with other frames, calibration files, options or code is
measured again, never kept; failed and dropped scans leave the dataset; scan ids stay
strings.  Small exact stripe frames (640x480) on a LocalCluster of 2 worker processes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _measure_synth import CAM, PLANE, write_scan  # noqa: E402
from _cli import lightplane, one_error_line  # noqa: E402

from lightplane import LightPlane  # noqa: E402
from lightplane.core.errors import LightplaneError  # noqa: E402
from lightplane.measure.batch import (  # noqa: E402
    DATASET_READ, LOCK_NAME, BatchOptions, measure_batch, open_dataset, read_points)
from lightplane.measure.scan import Motion, measure_scan, open_frames  # noqa: E402

N_FRAMES = 4
#: a second calibration of the same sensor: the plane moved by 0.5 mm
PLANE_B = LightPlane(PLANE.normal, PLANE.d + 0.5)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    d = tmp_path_factory.mktemp("frames")
    write_scan(d, N_FRAMES, "f")
    return d


@pytest.fixture(scope="module")
def reference(frames, tmp_path_factory):
    """`measure`'s points of the frames with each plane (single process)."""
    out = tmp_path_factory.mktemp("ref")
    ref = {}
    for name, plane in (("A", PLANE), ("B", PLANE_B)):
        measure_scan(open_frames([frames / "f"]), CAM, plane, out / f"{name}.npy", motion=Motion.none(), workers=1)
        ref[name] = np.load(out / f"{name}.npy")
        assert ref[name].size > 100
    assert not np.array_equal(ref["A"]["z"], ref["B"]["z"])
    return ref


def project(tmp_path, frames, ids=("a", "b"), plane=PLANE):
    """A manifest of scans ``ids`` (all the same frames) with ``plane`` in ``tmp_path/plane.json``."""
    plane.save(tmp_path / "plane.json", force=True)
    rows = "".join(f"{i},{frames / 'f'},{frames / 'camera.json'},plane.json\n" for i in ids)
    (tmp_path / "m.csv").write_text("id,input,camera,plane\n" + rows)
    return tmp_path / "m.csv"


def manifest_json(out):
    return json.loads((Path(out) / "manifest.json").read_text())


def partition_fingerprints(out):
    import pyarrow.parquet as pq

    return {p.relative_to(out).as_posix(): json.loads(pq.read_schema(p).metadata[b"lightplane"])["fingerprint"]
            for p in sorted(Path(out).glob("points/*/part-*.parquet"))}


def documented_read(out):
    """The read docs/batch.md and manifest.json give, run from inside the output folder."""
    import pyarrow  # noqa: F401  (named by the expression)
    import pyarrow.dataset  # noqa: F401

    cwd = os.getcwd()
    os.chdir(out)
    try:
        return eval(DATASET_READ).to_table()  # the exact text recorded in manifest.json
    finally:
        os.chdir(cwd)


def same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def write_lock(out, **fields):
    out.mkdir(exist_ok=True)
    holder = {"pid": os.getpid(), "host": socket.gethostname(), "started_utc": "2024-01-01T00:00:00+00:00",
              "started_unix": time.time(), "token": "x"}
    holder.update(fields)
    (out / LOCK_NAME).write_text(json.dumps(holder))


# ----------------------------------------------------------------------------- the lock
def test_second_run_is_refused_while_the_first_holds_the_lock(frames, client, tmp_path):
    m = project(tmp_path, frames, ids=("a",))
    out = tmp_path / "out"
    started, go, seen, result = threading.Event(), threading.Event(), {}, {}

    def hold(sid, done, total):
        if not started.is_set():
            seen["manifest"] = manifest_json(out)["status"]
            started.set()
            assert go.wait(60)

    def first():
        result["r"] = measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client, progress=hold)

    t = threading.Thread(target=first)
    t.start()
    try:
        assert started.wait(60)
        holder = json.loads((out / LOCK_NAME).read_text())
        assert holder["pid"] == os.getpid() and holder["host"] == socket.gethostname()
        with pytest.raises(LightplaneError) as e:
            measure_batch(m, out, client=client)
        assert f"pid {os.getpid()}" in str(e.value) and "another measure-batch run" in str(e.value)
        assert "\n" not in str(e.value)
    finally:
        go.set()
        t.join(60)
    assert seen["manifest"] == "in progress"
    assert result["r"].status == "ok" and not (out / LOCK_NAME).exists()
    assert manifest_json(out)["status"] == "ok"


def test_lock_of_a_dead_process_is_taken_over(frames, client, reference, tmp_path):
    m = project(tmp_path, frames, ids=("a",))
    out = tmp_path / "out"
    gone = dead_pid()
    write_lock(out, pid=gone)
    notes = []
    r = measure_batch(m, out, client=client, on_notice=notes.append)
    assert r.status == "ok" and same(read_points(out, "a"), reference["A"])
    assert len(notes) == 1 and f"pid {gone}" in notes[0] and "stale" in notes[0] and "\n" not in notes[0]
    assert r.notes == notes and manifest_json(out)["notes"] == notes
    assert not (out / LOCK_NAME).exists()
    if Path(f"/proc/{os.getpid()}/stat").is_file():  # a live pid that another process now has: stale too
        write_lock(out, process_start="1")
        notes.clear()
        assert measure_batch(m, out, client=client, on_notice=notes.append).status == "ok"
        assert len(notes) == 1 and "stale" in notes[0]


def test_lock_from_another_host_is_broken_only_when_asked(frames, client, tmp_path):
    m = project(tmp_path, frames, ids=("a",))
    out = tmp_path / "out"
    write_lock(out, host="scanner-07.example", started_unix=time.time() - 3 * 3600 - 60)
    with pytest.raises(LightplaneError) as e:
        measure_batch(m, out, client=client)
    msg = str(e.value)
    assert "scanner-07.example" in msg and "3 h 1 min ago" in msg and "--break-lock" in msg
    assert (out / LOCK_NAME).exists() and not (out / "manifest.json").exists()  # nothing touched
    (out / LOCK_NAME).write_bytes(b"\x00garbage")  # unreadable: refused as well
    with pytest.raises(LightplaneError, match="--break-lock"):
        measure_batch(m, out, client=client)
    write_lock(out, host="scanner-07.example")
    notes = []
    r = measure_batch(m, out, batch=BatchOptions(break_lock=True), client=client, on_notice=notes.append)
    assert r.status == "ok" and "broke the lock" in notes[0] and "scanner-07.example" in notes[0]
    assert not (out / LOCK_NAME).exists()


def test_command_refuses_a_held_lock_in_one_line(frames, client, tmp_path):
    m = project(tmp_path, frames, ids=("a",))
    out = tmp_path / "out"
    write_lock(out, host="scanner-07.example")
    r = lightplane("measure-batch", m, "-o", out, "--scheduler", client.scheduler.address, timeout=120)
    one_error_line(r, "scanner-07.example", "--break-lock")
    r = lightplane("measure-batch", m, "-o", out, "--scheduler", client.scheduler.address, "--break-lock",
                   timeout=120)
    assert r.returncode == 0, r.stderr
    assert "warning:" in r.stderr and "broke the lock" in r.stderr and "status ok" in r.stdout
    assert not (out / LOCK_NAME).exists()


# ----------------------------------------------------------------------------- stopped runs, fingerprints
def test_stopped_rerun_after_a_calibration_change_is_never_ok(frames, client, reference, tmp_path):
    m = project(tmp_path, frames, ids=("a", "b"))
    out = tmp_path / "out"
    opts = BatchOptions(chunk_frames=1)
    assert measure_batch(m, out, batch=opts, client=client).status == "ok"
    sha_a = hashlib.sha256((tmp_path / "plane.json").read_bytes()).hexdigest()
    assert {f["calibration_sha256"]["plane"] for f in partition_fingerprints(out).values()} == {sha_a}

    project(tmp_path, frames, ids=("a", "b"), plane=PLANE_B)  # the plane file changes
    sha_b = hashlib.sha256((tmp_path / "plane.json").read_bytes()).hexdigest()
    state = {}

    def killed(sid, done, total):  # the run dies once scan a's chunks are submitted, before b is looked at
        state["manifest"] = manifest_json(out)["status"]
        state["lock"] = (out / LOCK_NAME).exists()
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError, match="killed"):
        measure_batch(m, out, batch=opts, client=client, progress=killed)
    assert state["manifest"] == "in progress" and state["lock"]  # what a kill at that moment leaves
    doc = manifest_json(out)
    assert doc["status"] == "failed" and "stopped before its end" in doc["error"]
    assert not (out / LOCK_NAME).exists()
    time.sleep(0.5)  # a task cancelled while running ends (it may no longer write: the lock is gone)
    left = partition_fingerprints(out)
    new = [k for k in left if k.startswith("points/scan=a/")]
    assert all(left[k]["calibration_sha256"]["plane"] == sha_b for k in new)  # a's old partitions: removed
    assert [left[f"points/scan=b/part-{k}.parquet"]["calibration_sha256"]["plane"] for k in range(N_FRAMES)] \
        == [sha_a] * N_FRAMES  # b: still plane A's, in a dataset that mixes both; the manifest says so

    r = measure_batch(m, out, batch=opts, client=client)
    assert r.status == "ok" and r.partitions_reused == len(new) and r.partitions_written == 2 * N_FRAMES - len(new)
    fps = partition_fingerprints(out)
    assert len(fps) == 2 * N_FRAMES and {f["calibration_sha256"]["plane"] for f in fps.values()} == {sha_b}
    for sid in ("a", "b"):
        assert same(read_points(out, sid), reference["B"])


def test_partition_with_another_fingerprint_is_measured_again(frames, client, reference, tmp_path):
    m = project(tmp_path, frames, ids=("a",))
    out = tmp_path / "out"
    assert measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client).partitions_written == 2
    # same calibration, rewritten (new bytes: a key added): its content hash changes, so every partition
    plane = json.loads((tmp_path / "plane.json").read_text())
    plane["note"] = "re-saved"
    (tmp_path / "plane.json").write_text(json.dumps(plane))
    r = measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client)
    assert r.partitions_written == 2 and r.partitions_reused == 0
    # a frame touched (same bytes, new modification time): the scan's partitions are measured again
    f0 = sorted((frames / "f").glob("*.png"))[0]
    st = f0.stat()
    try:
        os.utime(f0, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
        r = measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client)
        assert r.partitions_written == 2 and r.partitions_reused == 0
    finally:
        os.utime(f0, ns=(st.st_atime_ns, st.st_mtime_ns))
    r = measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client)
    assert r.partitions_written == 2 and r.partitions_reused == 0
    r = measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client)  # nothing changed
    assert r.partitions_written == 0 and r.partitions_reused == 2
    fp = next(iter(partition_fingerprints(out).values()))
    assert set(fp) >= {"frames", "calibration_sha256", "motion", "options", "code", "chunk", "layout"}
    assert fp["code"]["lightplane"] and fp["frames"]["count"] == N_FRAMES
    assert same(read_points(out, "a"), reference["A"])


# ----------------------------------------------------------------------------- failed and dropped scans
def test_failed_and_dropped_scans_leave_the_dataset(frames, client, reference, tmp_path):
    m = project(tmp_path, frames, ids=("a", "b", "c"))
    out = tmp_path / "out"
    assert measure_batch(m, out, batch=BatchOptions(ply=True), client=client).status == "ok"
    assert documented_read(out).num_rows == 3 * reference["A"].size
    # b's camera is gone, c left the manifest, and a stray folder appeared under points/
    (tmp_path / "m.csv").write_text("id,input,camera,plane\n"
                                    f"a,{frames / 'f'},{frames / 'camera.json'},plane.json\n"
                                    f"b,{frames / 'f'},no-such-camera.json,plane.json\n")
    (out / "points" / "scan=old").mkdir()  # a scan of some other manifest
    (out / "points" / "scan=old" / "part-0.parquet").write_bytes((out / "points" / "scan=a" / "part-0.parquet")
                                                                 .read_bytes())
    r = measure_batch(m, out, batch=BatchOptions(ply=True), client=client)
    doc = manifest_json(out)
    assert r.status == "failed" == doc["status"] and [s["status"] for s in doc["scans"]] == ["ok", "failed"]
    t = documented_read(out)
    assert t.num_rows == reference["A"].size and set(t.column("scan").to_pylist()) == {"a"}
    assert read_points(out, "b").size == 0 and read_points(out, "c").size == 0
    listed = {d["path"]: d["reason"] for d in doc["set_aside"]}
    assert set(listed) == {"set-aside/points/scan=b", "set-aside/points/scan=c", "set-aside/points/scan=old",
                           "set-aside/ply/b.ply", "set-aside/ply/c.ply"}
    assert "no-such-camera" in listed["set-aside/points/scan=b"] and "not a scan" in listed["set-aside/points/scan=c"]
    assert sorted(p.name for p in (out / "ply").iterdir()) == ["a.ply"]
    assert doc["scans"][1]["partitions"] == [] and doc["scans"][1]["set_aside"] == "set-aside/points/scan=b"
    # c comes back unchanged: its partitions are taken back from set-aside/, not measured again
    m = project(tmp_path, frames, ids=("a", "c"))
    r = measure_batch(m, out, client=client)
    assert r.status == "ok" and r.partitions_written == 0 and r.partitions_reused == 2
    assert same(read_points(out, "c"), reference["A"]) and documented_read(out).num_rows == 2 * reference["A"].size
    assert {d["path"] for d in manifest_json(out)["set_aside"]} == {
        "set-aside/points/scan=b", "set-aside/points/scan=old", "set-aside/ply/a.ply", "set-aside/ply/b.ply",
        "set-aside/ply/c.ply"}  # a.ply: --ply was off this time
    assert manifest_json(out)["set_aside"][0]["reason"].startswith("the scan failed")  # kept from the last run


def test_scan_that_fails_mid_way_leaves_no_partition(frames, client, tmp_path):
    import cv2

    bad = tmp_path / "bad"
    bad.mkdir()
    for q in sorted((frames / "f").glob("*.png")):
        (bad / q.name).write_bytes(q.read_bytes())
    cv2.imwrite(str(bad / "f99.png"), np.zeros((240, 320), np.uint8))  # the last chunk's frame: another size
    PLANE.save(tmp_path / "plane.json")
    (tmp_path / "m.csv").write_text(f"id,input,camera,plane\nbad,{bad},{frames / 'camera.json'},plane.json\n"
                                    f"good,{frames / 'f'},{frames / 'camera.json'},plane.json\n")
    out = tmp_path / "out"
    r = measure_batch(tmp_path / "m.csv", out, batch=BatchOptions(chunk_frames=2), client=client)
    bad_entry = r.scans[0]
    assert bad_entry["status"] == "failed" and bad_entry["partitions_written"] == 2  # two chunks were written
    assert not (out / "points" / "scan=bad").exists()
    assert sorted(p.name for p in (out / "set-aside" / "points" / "scan=bad").iterdir()) == [
        "part-0.parquet", "part-1.parquet"]
    assert set(open_dataset(out).to_table().column("scan").to_pylist()) == {"good"}


# ----------------------------------------------------------------------------- scan ids
def test_ids_1_and_01_stay_distinct(frames, client, reference, tmp_path):
    import pyarrow as pa
    import pyarrow.dataset as pds

    PLANE.save(tmp_path / "plane.json")
    (tmp_path / "m.csv").write_text("id,input,camera,plane\n"
                                    f"1,{frames / 'f'}/f0[01].png,{frames / 'camera.json'},plane.json\n"
                                    f"01,{frames / 'f'},{frames / 'camera.json'},plane.json\n")
    out = tmp_path / "out"
    assert measure_batch(tmp_path / "m.csv", out, client=client).status == "ok"
    import pyarrow.parquet as pq

    schema = pq.read_schema(next((out / "points").rglob("*.parquet")))  # units and frame travel with the points
    assert json.loads(schema.metadata[b"units"])["x"] == "mm" and schema.field("u").metadata[b"unit"] == b"px"
    assert schema.metadata[b"frame"] == b"x y z in mm (camera frame)"
    n1, n01 = read_points(out, "1").size, read_points(out, "01").size
    assert n01 == reference["A"].size and 0 < n1 < n01
    for t in (documented_read(out), open_dataset(out).to_table()):
        assert t.schema.field("scan").type == pa.string()
        ids = t.column("scan").to_pylist()
        assert ids.count("1") == n1 and ids.count("01") == n01
    # a read that infers the key (all ids look like integers: int32) cannot merge them silently
    try:
        t = pds.dataset(out / "points", format="parquet", partitioning="hive").to_table()
    except (pa.ArrowTypeError, pa.ArrowInvalid):
        pass
    else:
        assert len(set(t.column("scan").to_pylist())) == 2


# ----------------------------------------------------------------------------- a real kill, a real SIGTERM
@contextlib.contextmanager
def busy_workers(client, tmp_path):
    """Every worker busy with a task that waits for a file, made when the block ends."""
    gate = tmp_path / "gate"

    def wait_for(path):  # local: pickled by value (the workers cannot import this module)
        import os
        import time

        while not os.path.exists(path):
            time.sleep(0.02)

    workers = list(client.scheduler_info()["workers"])
    futs = [client.submit(wait_for, str(gate), pure=False, workers=[w], allow_other_workers=False)
            for w in workers]
    t0 = time.monotonic()
    while sum(len(v) for v in client.processing().values()) < len(workers) and time.monotonic() - t0 < 30:
        time.sleep(0.02)
    try:
        yield
    finally:
        gate.touch()
        client.gather(futs)
        gate.unlink()


def start_command(m, out, client, *extra):
    cmd = [sys.executable, "-m", "lightplane", "measure-batch", str(m), "-o", str(out), "--scheduler",
           client.scheduler.address, "--chunk-frames", "1", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_in_progress(out, proc, timeout=60.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            if manifest_json(out)["status"] == "in progress":
                return
        except (OSError, ValueError, KeyError):
            pass
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.01)
    raise AssertionError("the run never said 'in progress'")


def test_killed_command_leaves_in_progress_and_the_next_run_takes_over(frames, client, reference, tmp_path):
    m = project(tmp_path, frames, ids=("a", "b"))
    out = tmp_path / "out"
    assert measure_batch(m, out, batch=BatchOptions(chunk_frames=1), client=client).status == "ok"
    project(tmp_path, frames, ids=("a", "b"), plane=PLANE_B)
    with busy_workers(client, tmp_path):  # the command's tasks wait: it is killed in the middle of its run
        proc = start_command(m, out, client)
        wait_in_progress(out, proc)
        proc.kill()
        proc.communicate(timeout=30)
    assert manifest_json(out)["status"] == "in progress"  # not ok: the partitions may be mixed
    assert json.loads((out / LOCK_NAME).read_text())["pid"] == proc.pid
    notes = []
    r = measure_batch(m, out, batch=BatchOptions(chunk_frames=1), client=client, on_notice=notes.append)
    assert r.status == "ok" and "stale" in notes[0] and f"pid {proc.pid}" in notes[0]
    sha_b = hashlib.sha256((tmp_path / "plane.json").read_bytes()).hexdigest()
    assert {f["calibration_sha256"]["plane"] for f in partition_fingerprints(out).values()} == {sha_b}
    assert same(read_points(out, "a"), reference["B"]) and same(read_points(out, "b"), reference["B"])


def test_second_process_is_refused_and_a_terminated_command_releases_the_lock(frames, client, tmp_path):
    m = project(tmp_path, frames, ids=("a", "b"))
    out = tmp_path / "out"
    with busy_workers(client, tmp_path):
        proc = start_command(m, out, client)
        wait_in_progress(out, proc)
        with pytest.raises(LightplaneError, match=f"another measure-batch run writes there \\(pid {proc.pid} "):
            measure_batch(m, out, client=client)  # two processes: the second is refused
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "lightplane: error: interrupted"
    assert not (out / LOCK_NAME).exists()
    assert manifest_json(out)["status"] == "failed"


# ----------------------------------------------------------------------------- laser-off frames
def test_background_column_pairs_laser_off_frames_like_measure(frames, client, tmp_path):
    """A ``background`` column: each chunk reads its frames less their laser-off frames, the points
    bitwise those of ``measure --background`` (a static bright ridge that would take the rows
    without them); the laser-off frames are in the partitions' fingerprint (one touched: measured
    again); counts that do not pair fail the scan with the reason."""
    import cv2

    u = np.arange(CAM.width, dtype=float)[None, :]
    ridge = 240.0 * np.exp(-0.5 * ((u - 100.0) / 1.5) ** 2) * np.ones((CAM.height, 1))
    (tmp_path / "laser").mkdir()
    (tmp_path / "off").mkdir()
    for k, p in enumerate(sorted((frames / "f").glob("*.png"))):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(float)
        cv2.imwrite(str(tmp_path / "laser" / p.name), np.clip(np.rint(img + ridge), 0, 255).astype(np.uint8))
        cv2.imwrite(str(tmp_path / "off" / f"o{k}.png"), np.clip(np.rint(10.0 + ridge), 0, 255).astype(np.uint8))
    PLANE.save(tmp_path / "plane.json", force=True)
    m = tmp_path / "m.csv"
    m.write_text("id,input,camera,plane,background\n"
                 f"a,laser,{frames / 'camera.json'},plane.json,off\n"
                 f"b,laser,{frames / 'camera.json'},plane.json,{tmp_path / 'off' / 'o0.png'}\n")
    ref = tmp_path / "ref.npy"
    measure_scan(open_frames([tmp_path / "laser"], background=[tmp_path / "off"]), CAM, PLANE, ref,
                 motion=Motion.none(), workers=1)
    out = tmp_path / "out"
    r = measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client)
    assert r.status == "ok"
    pts = read_points(out, "a")
    assert same(pts, np.load(ref)) and pts.size > N_FRAMES * 300
    assert np.all(np.abs(pts["u"] - 100.0) > 20)            # not the ridge
    assert same(read_points(out, "b"), pts)                  # one laser-off frame for all: the same here
    fp = partition_fingerprints(out)
    assert all("laser_off_frames" in f for f in fp.values())
    off0 = tmp_path / "off" / "o0.png"
    st = off0.stat()
    os.utime(off0, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    r = measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client)
    assert r.partitions_written >= 1
    (tmp_path / "off" / "o1.png").unlink()
    r = measure_batch(m, out, batch=BatchOptions(chunk_frames=2), client=client)
    failed = {e["id"]: e for e in manifest_json(out)["scans"]}
    assert failed["a"]["status"] == "failed" and "3 laser-off frames for 4 frames" in failed["a"]["error"]
