"""Point-cloud files: every format reads back exactly what was written (docs/conventions.md §Point clouds)."""

from __future__ import annotations

import numpy as np
import pytest

from lightplane import LightplaneError
from lightplane.measure import pointcloud as pc
from lightplane.measure.pointcloud import POINT_DTYPE, PointSpool, make_records, read_cloud, write_cloud

VARIANTS = [("c.ply", {}), ("c_ascii.ply", {"ascii": True}), ("c.csv", {}), ("c.npy", {})]


def random_records(n: int = 2000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3)) * [80, 80, 30] + [0, 0, 470]
    sigma = np.where(rng.random(n) < 0.2, np.nan, rng.uniform(0, 0.05, n))  # NaN: no covariance
    rec = make_records(p, rng.integers(0, 2**32 - 1, n, dtype=np.uint64), rng.uniform(0, 255, n), sigma,
                       rng.uniform(-0.5, 1279.5, (n, 2)))
    rec["x"][:3] = [np.float32(1e-30), np.float32(-3.4e38), np.float32(0.1)]  # extreme float32 values survive
    return rec


def same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype.names == b.dtype.names and all(
        np.array_equal(a[f], b[f], equal_nan=True) and a[f].dtype == b[f].dtype for f in a.dtype.names)


@pytest.mark.parametrize("name,kw", VARIANTS)
def test_round_trip_exact(tmp_path, name, kw):
    rec = random_records()
    write_cloud(tmp_path / name, rec, comments=["provenance: test"], **kw)
    back = read_cloud(tmp_path / name)
    assert back.dtype == POINT_DTYPE and same(back, rec)


@pytest.mark.parametrize("name,kw", VARIANTS)
def test_streamed_spool_writes_the_same_file(tmp_path, monkeypatch, name, kw):
    rec = random_records(1000, seed=1)
    write_cloud(tmp_path / name, rec, **kw)
    monkeypatch.setattr(pc, "CHUNK_RECORDS", 77)  # many small chunks
    with PointSpool(tmp_path) as spool:
        for i in range(0, rec.size, 130):
            spool.append(rec[i:i + 130])
        spool.append(rec[:0])
        assert spool.count == rec.size
        write_cloud(tmp_path / ("s_" + name), spool, **kw)
        spool_path = spool.path
    assert not (tmp_path / spool_path).exists()  # the spool is removed
    assert (tmp_path / name).read_bytes() == (tmp_path / ("s_" + name)).read_bytes()


def test_ply_layout_is_standard(tmp_path):
    from plyfile import PlyData

    rec = random_records(10)
    write_cloud(tmp_path / "b.ply", rec, comments=["hello"])
    raw = (tmp_path / "b.ply").read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    units = b"comment units: x mm, y mm, z mm, frame index (0-based), intensity grey level, sigma_mm mm, u px, v px\n"
    assert header.startswith(b"ply\nformat binary_little_endian 1.0\n" + units + b"comment hello\nelement vertex 10\n")
    assert body == rec.astype(POINT_DTYPE).tobytes()  # little-endian records, nothing else
    ply = PlyData.read(str(tmp_path / "b.ply"))
    assert [p.name for p in ply["vertex"].properties] == list(POINT_DTYPE.names)
    assert ply.comments == [units[8:-1].decode(), "hello"]
    write_cloud(tmp_path / "a.ply", rec, ascii=True)
    assert PlyData.read(str(tmp_path / "a.ply")).text
    assert (tmp_path / "c.csv").exists() is False
    write_cloud(tmp_path / "c.csv", rec, comments=["lightplane point cloud: x y z in mm (camera frame)"])
    lines = (tmp_path / "c.csv").read_text().splitlines()
    assert lines[:3] == ["# " + units[8:-1].decode(), "# lightplane point cloud: x y z in mm (camera frame)",
                         "x,y,z,frame,intensity,sigma_mm,u,v"]
    back = read_cloud(tmp_path / "c.csv")  # the '#' lines skipped
    assert all(np.array_equal(back[n], rec[n], equal_nan=n not in ("frame",)) for n in POINT_DTYPE.names)


def test_empty_cloud(tmp_path):
    for name, kw in VARIANTS:
        write_cloud(tmp_path / name, np.empty(0, POINT_DTYPE), **kw)
        assert read_cloud(tmp_path / name).size == 0


def test_refuses_overwrite_and_bad_arguments(tmp_path):
    rec = random_records(5)
    write_cloud(tmp_path / "c.ply", rec)
    before = (tmp_path / "c.ply").read_bytes()
    with pytest.raises(LightplaneError, match="already exists"):
        write_cloud(tmp_path / "c.ply", rec[:2])
    assert (tmp_path / "c.ply").read_bytes() == before
    write_cloud(tmp_path / "c.ply", rec[:2], force=True)
    assert read_cloud(tmp_path / "c.ply").size == 2
    with pytest.raises(LightplaneError, match="suffix"):
        write_cloud(tmp_path / "c.xyz", rec)
    with pytest.raises(LightplaneError, match="ascii"):
        write_cloud(tmp_path / "d.csv", rec, ascii=True)
    with pytest.raises(LightplaneError, match="structured"):
        write_cloud(tmp_path / "e.ply", np.zeros((5, 3)))
    assert not (tmp_path / "d.csv").exists() and not (tmp_path / "e.ply").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.ply"]  # no temporary files left


def test_read_errors_name_the_file(tmp_path):
    with pytest.raises(LightplaneError, match="no such"):
        read_cloud(tmp_path / "none.ply")
    (tmp_path / "bad.ply").write_bytes(b"not a ply file")
    with pytest.raises(LightplaneError, match="bad.ply"):
        read_cloud(tmp_path / "bad.ply")
    (tmp_path / "bad.csv").write_text("1,2,3\n4,5,6\n")
    with pytest.raises(LightplaneError, match="name the columns"):
        read_cloud(tmp_path / "bad.csv")
    with pytest.raises(LightplaneError, match=r"\(N, 3\)"):
        make_records(np.zeros((4, 2)), 0)
