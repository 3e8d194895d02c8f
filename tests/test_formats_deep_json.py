"""A --pred JSON file nested past what Python's JSON reader follows (benchmark/formats/base.py Source.json):
one line naming the file, as any other file that is not JSON, under each reader that asks for it."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmark.formats.base import FormatError, Source
from benchmark.formats.openlanev2_submission import read_submission
from benchmark.formats.result_json import load_json, results_list


def deep(tmp_path: Path, suffix: str) -> Path:
    path = tmp_path / f"deep{suffix}"
    path.write_text('{"results": [' + "[" * 100_000 + "]" * 100_000 + "]}")
    return path


def test_a_json_file_nested_too_deeply_is_a_parse_error_of_that_file(tmp_path):
    source = Source.of(deep(tmp_path, ".json"))
    assert results_list(source) is None  # detection: not a JSON file with a results list
    with pytest.raises(FormatError) as refused:
        load_json(source)
    assert str(refused.value) == (
        f"{source.path}: not a JSON result file (arrays or objects nested too deeply to read)"
    )
    with pytest.raises(FormatError) as refused:
        read_submission(Source.of(deep(tmp_path, ".txt")))  # OpenLane-V2's JSON form
    assert str(refused.value) == (
        f"{tmp_path / 'deep.txt'}: neither a pickle nor JSON (arrays or objects nested too deeply to read)"
    )


def test_a_json_file_with_an_int_of_too_many_digits_is_a_parse_error_of_that_file(tmp_path):
    path = tmp_path / "big.json"
    path.write_text('{"results": [{"sample_token": "a", "vectors": [' + "9" * 5000 + "]}]}")
    with pytest.raises(FormatError) as refused:
        load_json(Source.of(path))
    assert str(refused.value).startswith(f"{path}: not a JSON result file (Exceeds the limit (4300 digits)")
