"""OpenLane-V2 submissions' restricted unpickler (benchmark/formats/openlanev2_submission.py) against pickles
that run nothing but blow up in memory or time: a memo slot far past the file's opcodes, a structure repeated
by memo references, a container within itself; lanes whose numbers a float cast would change (complex,
strings); a method that would break the report's lines."""

from __future__ import annotations

import pickle
import resource
import struct

import numpy as np
import pytest
from test_openlanev2_submission import REFUSED, refusal

from benchmark.formats.base import FormatError, Source
from benchmark.formats.openlanev2_submission import lanes_of, load_pickle, read_submission


def test_a_memo_slot_past_the_files_opcodes_is_refused_before_pickle_sizes_its_memo(tmp_path):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # EMPTY_DICT, LONG_BINPUT 2^27, STOP: pickle's C reader would fill a 2^28-slot memo (2 GiB)
    said = refusal(tmp_path, b"\x80\x04}r" + struct.pack("<I", 1 << 27) + b".")
    assert said == f"a pickle that stores in memo slot 134217728 after 2 opcodes, {REFUSED}"
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # kB: no 2 GiB memo
    said = refusal(tmp_path, b"(lp99999999999\n.")  # protocol 0's PUT
    assert said == f"a pickle that stores in memo slot 99999999999 after 2 opcodes, {REFUSED}"
    # the memo as picklers number it reads: protocol 0's PUT and protocol 2's BINPUT from 0 on
    for protocol in (0, 2):
        shared = [1.5]
        path = tmp_path / f"memo{protocol}.pkl"
        path.write_bytes(pickle.dumps({"a": shared, "b": shared, "c": ("x", "y")}, protocol=protocol))
        assert load_pickle(path) == {"a": [1.5], "b": [1.5], "c": ("x", "y")}


def test_a_structure_repeated_by_memo_references_past_the_files_size_is_refused(tmp_path):
    nested: list = []
    for _ in range(20):  # 2^20 lists walked from 200 bytes; 60 levels would never finish
        nested = [nested, nested]
    data = pickle.dumps({"method": "m", "results": {}, "x": nested}, protocol=4)
    assert len(data) < 300
    said = refusal(tmp_path, data)
    assert said == f"a pickle that repeats its parts by reference past the file's size, {REFUSED}"
    # one array of 8 MB referenced a million times (a lane's points, copied for each lane)
    lane = {"id": 1, "points": np.zeros((333_334, 3)), "confidence": 1.0}
    frame = {"predictions": {"lane_centerline": [lane] * 10**6}}
    data = pickle.dumps({"results": {("val", "s", "1"): frame}})
    assert len(data) < 20_000_000
    said = refusal(tmp_path, data)
    assert said == f"a pickle that repeats its parts by reference past the file's size, {REFUSED}"


def test_a_container_within_itself_is_refused_and_shared_small_parts_read(tmp_path):
    loop: list = []
    loop.append(loop)
    said = refusal(tmp_path, pickle.dumps({"results": loop}, protocol=4))
    assert said == f"a pickle that holds a list within itself, {REFUSED}"
    looped: dict = {}
    looped["self"] = looped
    said = refusal(tmp_path, pickle.dumps({"results": looped}, protocol=2))
    assert said == f"a pickle that holds a dict within itself, {REFUSED}"
    # a submitter's one empty list shared by every frame is no blow-up: read as the structure it is
    empty: list = []
    results = {("val", "s", str(i)): {"predictions": {"traffic_element": empty}} for i in range(1000)}
    path = tmp_path / "shared.pkl"
    path.write_bytes(pickle.dumps({"results": results}, protocol=4))
    loaded = load_pickle(path)["results"]
    assert len(loaded) == 1000 and all(r["predictions"]["traffic_element"] == [] for r in loaded.values())


@pytest.mark.parametrize("points, problem", [
    (np.array([[0, 0, 0], [1 + 5j, 0, 0]]), "not an array of real numbers (numpy reads it as complex128)"),
    ([["0", "0", "0"], ["1.5", "0", "0"]], "not an array of real numbers (numpy reads it as <U3)"),
    ([[0, 0, 0], [2**70, 0, 0]], "not an array of real numbers (numpy reads it as object)"),
])  # fmt: skip
def test_lane_points_a_float_cast_would_change_are_refused(tmp_path, points, problem):
    key = ("val", "s", "1")
    prediction = {"lane_centerline": [{"id": 1, "points": points, "confidence": 0.5}],
                  "topology_lclc": np.zeros((1, 1))}  # fmt: skip
    with pytest.raises(FormatError) as refused:
        lanes_of(prediction, tmp_path / "s.pkl", key)
    assert str(refused.value) == f"{tmp_path / 's.pkl'}: frame {key}: lane 1: points: {problem}"
    whole = {"id": 1, "points": [[0, 0, 0], [3, 4, 1]], "confidence": 1}
    integers = {**prediction, "lane_centerline": [whole]}
    assert lanes_of(integers, tmp_path / "s.pkl", key).points[0].tolist() == [[0, 0, 0], [3, 4, 1]]



@pytest.mark.parametrize("method", ["mine\n\n| forged | row |", "tab\there", "bell\x07"])
def test_a_method_that_is_not_one_printable_line_is_refused(tmp_path, method):
    # the method is written into report.md's tables: a newline there starts rows of the submitter's own
    path = tmp_path / "submission.pkl"
    path.write_bytes(pickle.dumps({"method": method, "results": {}}, protocol=4))
    with pytest.raises(FormatError) as refused:
        read_submission(Source.of(path))
    assert str(refused.value) == f'{path}: "method" {method!r} is not one line of printable text'
    path.write_bytes(pickle.dumps({"method": "TopoNet (r50)", "results": {}}, protocol=4))
    assert read_submission(Source.of(path)).method == "TopoNet (r50)"


@pytest.mark.parametrize("confidence, said", [
    (10**400, "an integer past a float's range"),  # float() overflows: a traceback before
    ("x" * 100, repr("x" * 100)[:60] + "..."),
], ids=["huge int", "long string"])  # fmt: skip
def test_a_confidence_that_is_no_float_is_one_short_line(tmp_path, confidence, said):
    key, path = ("val", "s", "1"), tmp_path / "s.pkl"
    prediction = {"lane_centerline": [{"id": 1, "points": np.zeros((2, 3)), "confidence": confidence}],
                  "topology_lclc": np.zeros((1, 1))}  # fmt: skip
    with pytest.raises(FormatError) as refused:
        lanes_of(prediction, path, key)
    assert str(refused.value) == f"{path}: frame {key}: lane 1: confidence: {said} is not a finite number"
