"""``--report DIR`` of the calibration commands: one folder per result, checked before any work."""

from __future__ import annotations

import pytest

from lightplane.cli._common import report_folders
from lightplane.core.errors import LightplaneError


def test_report_folders(tmp_path):
    assert report_folders(None, ["laser0", "laser1"], False) == {"laser0": None, "laser1": None}
    assert report_folders(None, [None], False) == {None: None}
    assert report_folders(tmp_path / "rep", [None], False) == {None: tmp_path / "rep"}
    assert report_folders(tmp_path / "rep", ["a", "b"], False) == {"a": tmp_path / "rep" / "a",
                                                                   "b": tmp_path / "rep" / "b"}
    (tmp_path / "rep" / "a").mkdir(parents=True)
    (tmp_path / "rep" / "a" / "index.html").write_text("x")
    with pytest.raises(LightplaneError, match="already exists"):
        report_folders(tmp_path / "rep", ["a", "b"], False)
    assert report_folders(tmp_path / "rep", ["a", "b"], True)["a"] == tmp_path / "rep" / "a"
    with pytest.raises(LightplaneError, match="parent folder"):
        report_folders(tmp_path / "no" / "rep", ["a", "b"], False)
    (tmp_path / "file").write_text("x")
    for names in ([None], ["a", "b"]):
        with pytest.raises(LightplaneError, match="not a folder"):
            report_folders(tmp_path / "file", names, False)
