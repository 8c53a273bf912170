"""read_manifest: UTF-8 with or without a byte-order mark and UTF-16 with one read alike;
any other bytes give one LightplaneError line (no traceback), whatever they are."""

from __future__ import annotations

import codecs
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _cli import lightplane, one_error_line  # noqa: E402

from lightplane.core.errors import LightplaneError  # noqa: E402
from lightplane.measure.batch import BatchScan, read_manifest  # noqa: E402

TEXT = ("id,input,camera,plane,direction\n"
        "# a comment\n"
        "tyre-1,frames/1,cam.json,plane.json,1;0;0\n"
        "\"é-2\",\"frames/é 2/*.png\",cam.json,plane.json,\n")
TEXT_OK = TEXT.replace('"é-2"', "e-2")


def test_utf8_with_and_without_bom_and_utf16_read_alike(tmp_path):
    p = tmp_path / "m.csv"
    p.write_bytes(TEXT_OK.encode("utf-8"))
    want = read_manifest(p)
    assert [s.id for s in want] == ["tyre-1", "e-2"] and want[1].input.endswith("frames/é 2/*.png")
    for name, data in (("utf-8 with BOM", codecs.BOM_UTF8 + TEXT_OK.encode("utf-8")),
                       ("utf-16 (BOM, native order)", TEXT_OK.encode("utf-16")),
                       ("utf-16-le with BOM", codecs.BOM_UTF16_LE + TEXT_OK.encode("utf-16-le")),
                       ("utf-16-be with BOM", codecs.BOM_UTF16_BE + TEXT_OK.encode("utf-16-be")),
                       ("windows line ends", codecs.BOM_UTF8 + TEXT_OK.replace("\n", "\r\n").encode("utf-8"))):
        p.write_bytes(data)
        assert read_manifest(p) == want, name


@pytest.mark.parametrize("data, words", [
    (TEXT_OK.encode("utf-16-le"), "NUL"),  # UTF-16 without its byte-order mark
    (TEXT_OK.encode("utf-32"), "UTF-32"),
    (TEXT_OK.replace("e-2", "é").encode("latin-1"), "not UTF-8"),
    (codecs.BOM_UTF16_LE + b"i\x00d\x00\x00\xd8", "not UTF-16"),  # a lone surrogate
    (b"id,input,camera,plane\n\"a,b,c,d\n" + b"x" * 200_000, "not a valid CSV"),  # a field past csv's limit
    (b"\xef\xbb\xbf", "empty"),
    (b'id,input,camera,"pla\nne"\na,b,c,d\n', "missing: plane"),  # a quoted line break in the header
    (b'id,input,camera,plane,"x\ry"\na,b,c,d,e\n', "unknown column"),
])
def test_other_bytes_give_one_clear_error(tmp_path, data, words):
    p = tmp_path / "m.csv"
    p.write_bytes(data)
    with pytest.raises(LightplaneError) as e:
        read_manifest(p)
    assert words in str(e.value) and "\n" not in str(e.value) and str(p) in str(e.value)


def test_command_says_one_line_for_a_manifest_it_cannot_decode(tmp_path):
    p = tmp_path / "m.csv"
    p.write_bytes(TEXT_OK.encode("utf-32"))
    r = lightplane("measure-batch", p, "-o", tmp_path / "out", "--local-workers", "1", timeout=120)
    one_error_line(r, "UTF-32")
    assert not (tmp_path / "out").exists()


def valid(scans) -> bool:
    import re

    ids = [s.id for s in scans]
    return (isinstance(scans, list) and len(scans) > 0 and len(set(ids)) == len(ids)
            and all(isinstance(s, BatchScan) and re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", s.id)
                    and s.input and s.camera and s.plane for s in scans))


ENCODINGS = ["utf-8", "utf-8-sig", "utf-16", "utf-16-le", "utf-16-be", "utf-32", "latin-1", "cp1252"]
cells = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=12)
ids = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9._-]{0,5}", fullmatch=True)
paths = st.text(alphabet=st.characters(blacklist_categories=("Cs", "Cc"), blacklist_characters=',"'),
                min_size=1, max_size=12)


@st.composite
def manifests(draw):
    """Bytes near a manifest: a header, rows of plausible or random cells, encoded one way or
    another, maybe cut short or with one byte changed."""
    if draw(st.integers(0, 4)):
        header = draw(st.sampled_from(["id,input,camera,plane", "id,input,camera,plane,step,direction,positions",
                                       "ID, Input ,camera,plane", "input,camera,plane", "id,input,camera,plane,x"]))
    else:
        header = ",".join(draw(st.lists(st.one_of(cells.map(lambda c: '"' + c.replace('"', '""') + '"'),
                                                  st.sampled_from(["id", "input", "camera", "plane"])), max_size=6)))
    rows = draw(st.lists(st.tuples(ids, paths, paths, paths).map(",".join), max_size=4))
    if draw(st.integers(0, 3)) == 0:
        rows.insert(draw(st.integers(0, len(rows))), ",".join(draw(st.lists(cells, max_size=8))))
    text = header + "\n" + "\n".join(rows) + draw(st.sampled_from(["", "\n", "\r\n"]))
    enc = draw(st.sampled_from(ENCODINGS[:3] if draw(st.integers(0, 2)) else ENCODINGS))  # mostly readable
    data = text.encode(enc, errors="replace")
    if draw(st.integers(0, 3)) == 0:
        data = data[:draw(st.integers(len(data) // 2, len(data)))]
    if data and draw(st.integers(0, 3)) == 0:
        i = draw(st.integers(0, len(data) - 1))
        data = data[:i] + bytes([draw(st.integers(0, 255))]) + data[i + 1:]
    return data


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(st.binary(max_size=400), manifests()))
def test_any_bytes_give_scans_or_one_lightplane_error(data):
    with tempfile.TemporaryDirectory(prefix="HB-manifest-") as d:
        p = Path(d) / "m.csv"
        p.write_bytes(data)
        try:
            scans = read_manifest(p)
        except LightplaneError as e:
            assert str(e) and "\n" not in str(e) and "\r" not in str(e)
        else:
            assert valid(scans), scans
