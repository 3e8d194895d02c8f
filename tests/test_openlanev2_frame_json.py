"""OpenLane-V2 frame files (pipeline/adapters/openlanev2.py) whose JSON Python reads but the reader must
refuse in one line naming the file and the record: nesting past Python's JSON reader, numbers written as
strings (a float cast parsed them)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.adapters.openlanev2 import numbers, read_json
from pipeline.errors import DataError


def test_a_frame_file_nested_too_deeply_is_one_line_naming_it(tmp_path):
    path = tmp_path / "315971916960141000.json"
    path.write_text('{"annotation": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(DataError) as refused:
        read_json(path)
    assert str(refused.value) == f"{path}: JSON: cannot be read: arrays or objects nested too deeply"


@pytest.mark.parametrize("value", [[["1", "2", "3"], ["4", "5", "6"]], [[1, 2, 3], [4, "5", None]]])
def test_points_written_as_strings_are_refused(tmp_path, value):
    with pytest.raises(DataError) as refused:
        numbers(value, (None, 3), tmp_path / "f.json", "annotation.lane_centerline[0].points")
    record = "annotation.lane_centerline[0].points"
    assert str(refused.value) == f"{tmp_path / 'f.json'}: {record}: is not an array of numbers"
    read = numbers([[1, 2, 3], [4.5, 5, 6]], (None, 3), tmp_path / "f.json", "points")
    assert read.dtype == np.float64 and read.tolist() == [[1, 2, 3], [4.5, 5, 6]]
    assert numbers([], (None, None), tmp_path / "f.json", "annotation.topology_lclc").shape == (0, 0)


def test_a_frame_file_with_an_int_of_too_many_digits_is_one_line_naming_it(tmp_path):
    path = tmp_path / "315971916960141000.json"
    path.write_text('{"timestamp": ' + "9" * 5000 + "}")  # Python's int reading stops at 4300 digits
    with pytest.raises(DataError) as refused:
        read_json(path)
    assert str(refused.value).startswith(f"{path}: JSON: cannot be read: Exceeds the limit (4300 digits)")
