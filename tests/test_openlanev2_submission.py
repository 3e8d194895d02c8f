"""OpenLane-V2 submissions (`cli score --format openlanev2`, benchmark/formats/openlanev2_submission.py): the
restricted unpickler against hostile pickles and with real numpy arrays, the JSON form, the matching of the
submission's keys to the prepared frames, the round trip of write_submission; and the graph of a frame's
predicted lanes with each edge's score from its lane's confidence."""

from __future__ import annotations

import codecs
import copyreg
import json
import os
import pickle
import pickletools
from pathlib import Path

import numpy as np
import pytest
from test_openlanev2_prepare import segment
from typer.testing import CliRunner

from benchmark.formats.base import FormatError
from benchmark.formats.openlanev2_submission import lanes_of, load_pickle, prediction_of, write_submission
from benchmark.score import score
from cli import app
from pipeline.geometry import Range
from pipeline.io import read_annotated_lanes, read_openlanev2_keys
from pipeline.lane_graph import graph_of_annotated, scored_graph_of_annotated
from pipeline.prepare import prepare
from pipeline.records import AnnotatedLanes
from pipeline.targets import TargetOptions


def lanes(points: list, links=None, confidence=None, ids=None) -> AnnotatedLanes:
    arrays = [np.asarray(p, np.float64) for p in points]
    links = np.zeros((len(arrays), len(arrays))) if links is None else np.asarray(links, np.float64)
    ids = ids if ids is not None else [str(i) for i in range(len(arrays))]
    conf = None if confidence is None else np.asarray(confidence, np.float64)
    return AnnotatedLanes(arrays, links, ids, conf)


def test_each_edge_of_a_predicted_graph_scores_its_lanes_highest_confidence():
    # ego frame: x forward, y left; the BEV graph has x right (= -y), y forward (= x)
    trunk = [[0, 0, 0], [10, 1, 0], [20, 0, 0]]  # bent at its middle point, which simplifying keeps
    twin = [[10, 1, 0], [20, 0, 0]]  # lies on the trunk's second edge
    branch = [[20, 0, 0], [30, -5, 0]]  # linked after the trunk: a fork at (20, 0)
    links = [[0, 0, 0.9], [0, 0, 0], [0, 0, 0]]
    predicted = lanes([trunk, twin, branch], links, [0.3, 0.8, 0.6])
    graph, scores = scored_graph_of_annotated(predicted, Range.parse("50x100"))
    xy = graph.xy
    by_edge = {(tuple(xy[s]), tuple(xy[d])): score for s, d, score in zip(graph.src, graph.dst, scores)}
    assert by_edge == {((0.0, 0.0), (-1.0, 10.0)): 0.3, ((-1.0, 10.0), (0.0, 20.0)): 0.8,
                       ((0.0, 20.0), (5.0, 30.0)): 0.6}  # fmt: skip
    unscored = graph_of_annotated(predicted, Range.parse("50x100"))
    assert all(np.array_equal(getattr(graph, f), getattr(unscored, f)) for f in ("x", "y", "src", "dst"))
    # clipped to 15 m ahead: the branch leaves the range with its score; the trunk and its twin, cut at the
    # border at the same point, share their last edge, which keeps the higher score
    short, short_scores = scored_graph_of_annotated(predicted, Range.parse("50x30"))
    xy = short.xy
    by_edge = {(tuple(xy[s]), tuple(xy[d])): score for s, d, score in zip(short.src, short.dst, short_scores)}
    assert by_edge == {((0.0, 0.0), (-1.0, 10.0)): 0.3, ((-1.0, 10.0), (-0.5, 15.0)): 0.8}
    # annotated lanes have no confidence: no scores; no lanes: no edges
    assert scored_graph_of_annotated(lanes([trunk]))[1] is None
    empty, empty_scores = scored_graph_of_annotated(lanes([], confidence=[]))
    assert len(empty.src) == 0 and empty_scores.shape == (0,)


# ---- the restricted unpickler --------------------------------------------------------------------------

MARKER_NAME = "ran"


class RunsCode:
    """Unpickled by pickle.load, this would run a shell command that writes a marker file."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


class Custom:
    """A class of the submitter's: not a dict, list, tuple, string, number or array."""


class Reduces:
    """Pickled as the given reduce value: a call numpy itself never writes."""

    def __init__(self, value) -> None:
        self.value = value

    def __reduce__(self):
        return self.value


def refusal(tmp_path: Path, data: bytes) -> str:
    path = tmp_path / "evil.pkl"
    path.write_bytes(data)
    with pytest.raises(FormatError) as refused:
        load_pickle(path)
    message = str(refused.value)
    assert "\n" not in message and message.startswith(f"{path}: ")
    return message.removeprefix(f"{path}: ")


REFUSED = ("refused: a submission holds only dicts, lists, tuples, strings, numbers and numpy arrays; "
           "nothing in it was run")


def test_a_pickle_that_would_run_code_is_refused_naming_the_global_and_nothing_runs(tmp_path):
    marker = tmp_path / MARKER_NAME
    submission = {"method": "m", "results": {("val", "s", "1"): {"predictions": RunsCode(marker)}}}
    for protocol in range(pickle.HIGHEST_PROTOCOL + 1):
        said = refusal(tmp_path, pickle.dumps(submission, protocol=protocol))
        assert said == f"a pickle that names the global {os.system.__module__}.system, {REFUSED}"
    assert not marker.exists()
    said = refusal(tmp_path, pickle.dumps({"results": Custom()}))
    assert said == f"a pickle that names the global {__name__}.Custom, {REFUSED}"


@pytest.mark.parametrize("data, global_name", [
    (b"cbuiltins\neval\n(S'1+1'\ntR.", "builtins.eval"),  # protocol 0: GLOBAL, REDUCE
    (b"(S'true'\nios\nsystem\n.", "os.system"),  # INST
    (b"\x80\x04\x8c\x08builtins\x94\x8c\x07getattr\x94\x93\x94.", "builtins.getattr"),  # STACK_GLOBAL
    (b"\x80\x02csubprocess\nPopen\nq\x00.", "subprocess.Popen"),
    (b"\x80\x02(cbuiltins\nexec\nX\x04\x00\x00\x00passo.", "builtins.exec"),  # OBJ
    (b"\x80\x02c__builtin__\nbytearray\n)R.", "__builtin__.bytearray"),  # Python 2's names, mapped by none
])  # fmt: skip
def test_hand_built_pickles_naming_any_other_global_are_refused(tmp_path, data, global_name):
    assert refusal(tmp_path, data) == f"a pickle that names the global {global_name}, {REFUSED}"


def test_a_global_registered_as_an_extension_is_refused(tmp_path):
    copyreg.add_extension("os", "system", 240)
    try:
        said = refusal(tmp_path, b"\x80\x02\x82\xf0X\x04\x00\x00\x00trueq\x00\x85R.")  # EXT1 240
    finally:
        copyreg.remove_extension("os", "system", 240)
    assert said == f"a pickle that names the global os.system, {REFUSED}"


reconstruct = np.core.multiarray._reconstruct


@pytest.mark.parametrize("value, what", [
    ((reconstruct, (np.dtype, (0,), b"b")), "calls numpy's _reconstruct with arguments numpy never writes "
                                            "(numpy.dtype, tuple, bytes)"),
    ((reconstruct, (np.ndarray, (10**12,), b"b")), "calls numpy's _reconstruct with arguments numpy never "
                                                   "writes (numpy.ndarray, tuple, bytes)"),
    ((np.ndarray, ((10**9,),)), "calls numpy.ndarray itself"),
    ((np.dtype, ("O", False, True)), "builds a numpy.dtype of 'O', not of numbers"),
    ((np.dtype, ("V8", False, True), (3, "|", None, None, None, 8, 1, 63)),
     "builds a numpy.dtype of 'V8', not of numbers"),  # a dtype whose flags say it holds objects
    ((np.dtype, ("f8", False, True), (3, "<", None, None, None, -1, -1, 63)),
     "gives numpy.dtype '<f8' a state numpy never writes"),
    ((reconstruct, (np.ndarray, (0,), b"b"), (1, (10**9,), np.dtype("f8"), False, b"\0" * 8)),
     "gives a numpy array's state 8 bytes for shape (1000000000,) of <f8"),
    ((np.core.multiarray.scalar, (np.dtype("f8"), b"\0" * 3)),
     "gives numpy's scalar 3 bytes for shape () of <f8"),
    ((bytes, (10**12,)), "calls bytes with arguments numpy never writes (int)"),
    ((codecs.encode, ("x", "zlib")), "calls _codecs.encode with arguments numpy never writes (str, str)"),
])  # fmt: skip
def test_what_the_unpickler_admits_takes_only_the_arguments_numpy_writes(tmp_path, value, what):
    assert refusal(tmp_path, pickle.dumps(Reduces(value), protocol=2)) == f"a pickle that {what}, {REFUSED}"


def test_an_admitted_global_cannot_be_rebuilt_and_a_persistent_id_is_refused(tmp_path):
    said = refusal(tmp_path, b"\x80\x02cnumpy\ndtype\n}b.")  # BUILD on the global itself
    assert said == f"a pickle that rebuilds numpy.dtype, {REFUSED}"
    said = refusal(tmp_path, b"\x80\x02cnumpy\ndtype\nN}\x86b.")  # (state, slot state): setattr otherwise
    assert said == f"a pickle that rebuilds numpy.dtype, {REFUSED}"
    said = refusal(tmp_path, b"\x80\x02X\x01\x00\x00\x00aQ.")
    assert said == f"a pickle that holds a persistent id, {REFUSED}"
    assert refusal(tmp_path, pickle.dumps({"a": 1})[:-3]) == (
        "not a readable pickle (UnpicklingError: pickle data was truncated)"
    )


ARRAYS = {
    "f4": np.arange(12, dtype="f4").reshape(4, 3) / 7, "f8": np.linspace(-1, 1, 9).reshape(3, 3),
    ">f8": np.arange(6, dtype=">f8"), "i8": np.arange(-3, 3), "u1": np.arange(5, dtype="u1"),
    "b1": np.array([True, False, True]), "c16": np.array([1 + 2j, -3j]), "empty": np.zeros((0, 3)),
    "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)), "f2": np.array([0.5, 2.0], "f2"),
}  # fmt: skip
SCALARS = {"f4": np.float32(0.25), "f8": np.float64(-1.5), "i4": np.int32(-7), "u8": np.uint64(2**63),
           "b": np.bool_(True)}  # fmt: skip


def numpy2_names(data: bytes) -> bytes:
    """A pickle as numpy 2 writes it: numpy.core's modules named numpy._core (frames dropped, which a reader
    does without: they would no longer fit)."""
    frames = [position for opcode, _, position in pickletools.genops(data) if opcode.name == "FRAME"]
    for position in reversed(frames):
        data = data[:position] + data[position + 9 :]
    for old in ("numpy.core.multiarray", "numpy.core.numeric"):
        new = old.replace("numpy.core", "numpy._core")
        data = data.replace(bytes([0x8C, len(old)]) + old.encode(), bytes([0x8C, len(new)]) + new.encode())
        data = data.replace(f"c{old}\n".encode(), f"c{new}\n".encode())
    return data


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
@pytest.mark.parametrize("names", ["numpy 1", "numpy 2"])
def test_numpy_arrays_and_scalars_are_rebuilt_exactly_under_either_numpys_names(tmp_path, protocol, names):
    content = {"arrays": ARRAYS, "scalars": SCALARS, "plain": [1, 2.5, "x", None, True, ("a", "b", "c")]}
    data = pickle.dumps(content, protocol=protocol)
    if names == "numpy 2":
        data = numpy2_names(data)
        assert b"numpy._core" in data and b"numpy.core" not in data
    path = tmp_path / "arrays.pkl"
    path.write_bytes(data)
    loaded = load_pickle(path)
    for name, array in ARRAYS.items():
        got = loaded["arrays"][name]
        assert type(got) is np.ndarray and got.dtype == array.dtype and got.shape == array.shape, name
        assert np.array_equal(got, array) and got.flags.writeable, name
    for name, value in SCALARS.items():
        got = loaded["scalars"][name]
        assert type(got) is type(value) and got == value, name
    assert loaded["plain"] == content["plain"]


# ---- submissions scored against prepared OpenLane-V2 frames --------------------------------------------


@pytest.fixture(scope="module")
def prepared(tmp_path_factory) -> Path:
    """OpenLane-V2 frame files (test_openlanev2_prepare's fork and merge) prepared: segment seg-a's 3 frames
    in train, seg-b's 2 and seg-c's 2 in val."""
    root, out = tmp_path_factory.mktemp("olv2"), tmp_path_factory.mktemp("prepared") / "data"
    segment(root, "seg-a", 3, "train")
    segment(root, "seg-b", 2, "val")
    segment(root, "seg-c", 2, "val", translation=(500.0, 200.0, 10.0))
    prepare("openlanev2", root, out, TargetOptions())
    return out


def predicted(data: Path, split: str | None = None) -> dict[tuple[str, str, str], AnnotatedLanes]:
    """The prepared frames' annotated lanes as predictions, by key: distinct confidences, links as
    probabilities (0.9 linked, 0.2 not)."""
    keys, annotated = read_openlanev2_keys(data), read_annotated_lanes(data)
    return {
        keys[f]: AnnotatedLanes(lanes.points, np.where(lanes.links > 0, 0.9, 0.2), lanes.ids,
                                np.linspace(0.95, 0.5, len(lanes)))  # fmt: skip
        for f, lanes in annotated.items() if split is None or keys[f][0] == split
    }


def as_json(frames: dict, path: Path) -> Path:
    """The same submission in the JSON form."""
    records = [{"split": key[0], "segment_id": key[1], "timestamp": key[2],
                "predictions": {name: (value.tolist() if isinstance(value, np.ndarray) else value)
                                for name, value in plain(prediction_of(lanes)).items()}}
               for key, lanes in frames.items()]  # fmt: skip
    path.write_text(json.dumps({"method": "mine", "results": records}))
    return path


def plain(prediction: dict) -> dict:
    lanes = [{**lane, "points": lane["points"].tolist()} for lane in prediction["lane_centerline"]]
    return {**prediction, "lane_centerline": lanes}


def test_write_submission_round_trips_through_the_reader_in_the_documented_structure(prepared, tmp_path):
    frames = predicted(prepared, "val")
    path = tmp_path / "submission.pkl"
    write_submission(path, "mine", frames)
    content = load_pickle(path)
    assert content["method"] == "mine" and set(content["results"]) == set(frames)
    for key, lanes in frames.items():
        prediction = content["results"][key]["predictions"]
        assert [lane["id"] for lane in prediction["lane_centerline"]] == [int(i) for i in lanes.ids]
        assert prediction["traffic_element"] == [] and prediction["topology_lcte"].shape == (len(lanes), 0)
        read = lanes_of(prediction, path, key)
        assert read.ids == lanes.ids and np.array_equal(read.links, lanes.links)
        assert np.array_equal(read.confidence, lanes.confidence)
        assert all(np.array_equal(a, b) for a, b in zip(read.points, lanes.points))
    # ids that are not ints' stay strings; annotated lanes (no confidence) are written with 1.0
    key = ("val", "s", "1")
    write_submission(path, "m", {key: lanes_made([[[0, 0, 0], [1, 0, 0]]], ids=["007"])})
    lane = load_pickle(path)["results"][key]["predictions"]["lane_centerline"][0]
    assert lane["id"] == "007" and lane["confidence"] == 1.0
    with pytest.raises(ValueError, match="key \\('val', 's'\\) is not \\(split, segment_id, timestamp\\)"):
        write_submission(tmp_path / "bad.pkl", "m", {("val", "s"): lanes_made([])})
    assert not (tmp_path / "bad.pkl").exists()


def test_a_submission_scores_its_frames_and_the_json_form_scores_alike(prepared, tmp_path):
    frames = predicted(prepared, "val")
    pickled = tmp_path / "submission.pkl"
    write_submission(pickled, "mine", frames)
    result = score(pickled, prepared, bootstrap=0)  # auto: told by its content
    assert result["external"]["format"] == "openlanev2" and result["splits"] == ["val"]
    assert (result["frames"], result["frames_predicted"], result["frames_missing"]) == (4, 4, 0)
    assert result["external"]["lanes_read"] == sum(len(lanes) for lanes in frames.values())
    assert result["external"]["not_computed"] == ["DET_t", "TOP_lt", "OLS"]
    assert result["directed"]["topo"]["f1"] == 1.0 and result["miou"] == 1.0  # the annotated lanes themselves
    in_json = score(as_json(frames, tmp_path / "submission.json"), prepared, bootstrap=0)
    assert in_json["external"]["format"] == "openlanev2"
    assert {k: v for k, v in in_json.items() if k not in ("pred", "external")} == {
        k: v for k, v in result.items() if k not in ("pred", "external")}  # fmt: skip


def test_frames_the_submission_lacks_are_empty_and_split_picks_the_keys_that_count(prepared, tmp_path):
    frames = predicted(prepared)
    seg_b = {key: lanes for key, lanes in frames.items() if key[1] == "seg-b"}
    path = tmp_path / "b.pkl"
    write_submission(path, "mine", seg_b)
    result = score(path, prepared, bootstrap=0)
    assert (result["frames"], result["frames_predicted"], result["frames_missing"]) == (4, 2, 2)
    assert result["directed"]["topo"]["recall"] < 1.0 == result["directed"]["topo"]["precision"]
    # with --split, the train keys are not counted (nor refused); an unknown train key neither
    train_too = {**seg_b, **{k: v for k, v in frames.items() if k[0] == "train"},
                 ("train", "seg-x", "1"): frames[next(iter(seg_b))]}  # fmt: skip
    write_submission(path, "mine", train_too)
    split = score(path, prepared, split="val", bootstrap=0)
    assert (split["frames"], split["frames_predicted"], split["frames_missing"]) == (4, 2, 2)
    assert split["external"]["frames_in_file"] == 6
    assert split["directed"] == result["directed"]
    with pytest.raises(FormatError, match=r"b.pkl: frame \('train', 'seg-x', '1'\) is not in the ground"):
        score(path, prepared, bootstrap=0)  # without --split every key counts


def test_a_key_of_no_prepared_frame_is_refused_naming_the_first(prepared, tmp_path):
    frames = predicted(prepared, "val")
    lanes = next(iter(frames.values()))
    frames[("val", "seg-z", "2")] = frames[("val", "seg-z", "1")] = lanes
    path = tmp_path / "unknown.pkl"
    write_submission(path, "mine", frames)
    with pytest.raises(FormatError) as refused:
        score(path, prepared, split="val", bootstrap=0)
    assert str(refused.value) == (
        f"{path}: frame ('val', 'seg-z', '1') (and 1 more) is not in the ground truth {prepared}"
    )


def lanes_made(points: list, links=None, confidence=None, ids=None) -> AnnotatedLanes:
    return lanes(points, links, confidence, ids)


GOOD_LANE = {"id": 1, "points": np.array([[0.0, 0, 0], [5, 0, 0]]), "confidence": 0.5}


@pytest.mark.parametrize("prediction, problem", [
    ({"topology_lclc": np.zeros((0, 0))}, 'no "lane_centerline" list in its predictions'),
    ({"lane_centerline": [GOOD_LANE]}, 'no "topology_lclc" in its predictions'),
    ({"lane_centerline": [{"id": 1, "points": np.zeros((2, 3))}], "topology_lclc": np.zeros((1, 1))},
     'lane_centerline[0] is not {"id", "points", "confidence"}'),
    ({"lane_centerline": [{**GOOD_LANE, "points": np.zeros((4, 2))}], "topology_lclc": np.zeros((1, 1))},
     "lane 1: points of shape (4, 2), not (n, 3) with n >= 2"),
    ({"lane_centerline": [{**GOOD_LANE, "points": np.zeros((1, 3))}], "topology_lclc": np.zeros((1, 1))},
     "lane 1: points of shape (1, 3), not (n, 3) with n >= 2"),
    ({"lane_centerline": [{**GOOD_LANE, "points": np.array([[0, 0, 0], [np.nan, 1, 0]])}],
      "topology_lclc": np.zeros((1, 1))}, "lane 1: points: not an array of finite numbers"),
    ({"lane_centerline": [{**GOOD_LANE, "points": [[0, 0, 0], [1, 1]]}], "topology_lclc": np.zeros((1, 1))},
     "lane 1: points: not an array of numbers"),
    ({"lane_centerline": [{**GOOD_LANE, "confidence": float("inf")}], "topology_lclc": np.zeros((1, 1))},
     "lane 1: confidence: inf is not a finite number"),
    ({"lane_centerline": [{**GOOD_LANE, "confidence": "0.5"}], "topology_lclc": np.zeros((1, 1))},
     "lane 1: confidence: '0.5' is not a finite number"),
    ({"lane_centerline": [GOOD_LANE, GOOD_LANE], "topology_lclc": np.zeros((2, 2))},
     "lane id '1' appears twice"),
    ({"lane_centerline": [{**GOOD_LANE, "id": 10**5000}], "topology_lclc": np.zeros((1, 1))},
     "lane_centerline[0]: id is an integer of more than 640 digits, not a string or an integer of at most "
     "640 digits"),
    ({"lane_centerline": [{**GOOD_LANE, "id": 1.0}], "topology_lclc": np.zeros((1, 1))},
     "lane_centerline[0]: id is a float, not a string or an integer of at most 640 digits"),
    ({"lane_centerline": [{**GOOD_LANE, "id": True}], "topology_lclc": np.zeros((1, 1))},
     "lane_centerline[0]: id is a bool, not a string or an integer of at most 640 digits"),
    ({"lane_centerline": [GOOD_LANE], "topology_lclc": np.zeros((1, 2))},
     "topology_lclc of shape (1, 2), not (1, 1) for its 1 lanes"),
    ({"lane_centerline": [GOOD_LANE], "topology_lclc": np.full((1, 1), np.nan)},
     "topology_lclc: not an array of finite numbers"),
])  # fmt: skip
def test_a_malformed_frame_is_one_line_naming_the_file_and_the_frame(prepared, tmp_path, prediction, problem):
    key = next(iter(read_openlanev2_keys(prepared).values()))
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps({"method": "m", "results": {key: {"predictions": prediction}}}))
    with pytest.raises(FormatError) as refused:
        score(path, prepared, bootstrap=0)
    assert str(refused.value) == f"{path}: frame {key}: {problem}"


def test_lane_ids_are_strings_and_integers_of_at_most_640_digits_as_text():
    """numpy's integers read as Python's; the longest integer kept is still turned into text by any Python."""
    prediction = {"lane_centerline": [{**GOOD_LANE, "id": i} for i in (np.int64(-7), "7a", 10**640 - 1)],
                  "topology_lclc": np.zeros((3, 3))}  # fmt: skip
    assert lanes_of(prediction, Path("p.pkl"), ("val", "s", "1")).ids == ["-7", "7a", "9" * 640]


def test_what_is_not_a_submission_or_its_data_is_refused_in_one_line(prepared, synth_prepared, tmp_path):
    path = tmp_path / "s.pkl"
    write_submission(path, "mine", predicted(prepared, "val"))
    with pytest.raises(FormatError, match="s.pkl: an OpenLane-V2 submission, scored against OpenLane-V2 "
                       r"frames; the ground truth \S+ is av2 data: pass one that cli prepare --dataset "
                       "openlanev2 made"):
        score(path, synth_prepared["av2"], bootstrap=0)  # fmt: skip
    with pytest.raises(FormatError, match="--min-score, --sweep: only for a result file of MapTRv2 / "
                       "LaneGAP or CGNet"):
        score(path, prepared, min_score=0.5, sweep=True, bootstrap=0)  # fmt: skip
    bad_key = tmp_path / "k.pkl"
    bad_key.write_bytes(pickle.dumps({"results": {("val", "s", 1): {"predictions": {}}}}))
    with pytest.raises(FormatError, match=r"k.pkl: results key \('val', 's', 1\) is not \(split, "):
        score(bad_key, prepared, bootstrap=0)
    records = tmp_path / "r.json"
    records.write_text(json.dumps({"results": [{"split": "val", "segment_id": "s", "predictions": {}}]}))
    with pytest.raises(FormatError, match=r'r.json: results\[0\]: not \{"split", "segment_id", "timestamp"'):
        score(records, prepared, fmt="openlanev2", bootstrap=0)


def test_cli_score_says_the_missing_frames_and_what_is_not_computed(prepared, tmp_path):
    path = tmp_path / "b.pkl"
    write_submission(path, "mine", {k: v for k, v in predicted(prepared).items() if k[1] == "seg-b"})
    command = ["score", "--pred", str(path), "--gt", str(prepared), "--bootstrap", "0"]
    result = CliRunner().invoke(app, command)
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "(OpenLane-V2 submission, method mine)" in text
    assert "4 frames scored, 2 in the submission (12 lanes), 2 missing (scored as empty)" in text
    assert "not computed: DET_t, TOP_lt, OLS" in text
    # with OpenLane-V2's metric, whose notes say it too: said once
    with_metric = CliRunner().invoke(app, [*command, "--metric", "lanegap,openlanev2"])
    assert with_metric.exit_code == 0, with_metric.output
    text = " ".join(with_metric.output.split())
    assert "DET_l" in text and text.count("not computed") == 1 and text.count("TOP_lt") == 1


def test_a_submission_as_toponet_writes_it_is_read_with_its_traffic_elements_left_aside(prepared, tmp_path):
    """TopoNet's format_results: metadata strings, ids 10000 + i, float32 points (the annotated lanes' own,
    which float32 holds exactly), python float confidences, traffic elements with numpy scalars, float32
    topologies; pickled by mmcv.dump (protocol 4)."""
    keys = read_openlanev2_keys(prepared)
    results = {}
    for frame_id, lanes in read_annotated_lanes(prepared).items():
        if keys[frame_id][0] != "val":
            continue
        scores = np.linspace(0.9, 0.4, len(lanes), dtype=np.float32)
        results[keys[frame_id]] = {"predictions": {
            "lane_centerline": [{"id": 10000 + i, "points": p.astype(np.float32), "confidence": s.item()}
                                for i, (p, s) in enumerate(zip(lanes.points, scores))],
            "traffic_element": [{"id": 20000, "category": 1, "attribute": np.int64(3),
                                 "points": np.zeros((2, 2), np.float32), "confidence": np.float32(0.7)}],
            "topology_lclc": lanes.links.astype(np.float32),
            "topology_lcte": np.ones((len(lanes), 1), np.float32),
        }}  # fmt: skip
    submission = {"method": "TopoNet", "authors": [], "e-mail": "dummy",
                  "institution / company": "OpenDriveLab", "country / region": "CN", "results": results}
    path = tmp_path / "results.pkl"
    path.write_bytes(pickle.dumps(submission, protocol=4))
    result = score(path, prepared, bootstrap=0)
    assert result["external"]["method"] == "TopoNet" and result["frames_predicted"] == 4
    lanes_written = sum(len(record["predictions"]["topology_lclc"]) for record in results.values())
    assert result["external"]["lanes_read"] == lanes_written
    assert result["directed"]["topo"]["f1"] == 1.0 and result["miou"] == 1.0


def test_cli_score_refuses_a_pickle_that_would_run_code_in_one_line(prepared, tmp_path):
    marker = tmp_path / MARKER_NAME
    path = tmp_path / "submission.pkl"
    path.write_bytes(pickle.dumps({"method": "m", "results": {("val", "s", "1"): RunsCode(marker)}}))
    result = CliRunner().invoke(app, ["score", "--pred", str(path), "--gt", str(prepared)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 1 and not marker.exists()
    assert " ".join(result.output.split()) == (
        f"error: {path}: a pickle that names the global {os.system.__module__}.system, {REFUSED}"
    ), lines


def test_the_content_tells_a_pickle_from_the_json_form_whatever_the_name(prepared, tmp_path):
    frames = predicted(prepared, "val")
    named_pickle = as_json(frames, tmp_path / "results.pkl")  # JSON under a pickle's name: read as JSON
    assert score(named_pickle, prepared, bootstrap=0)["frames_predicted"] == 4
    old = tmp_path / "old.pkl"  # protocol 0 has no mark: auto does not take it, the line says what to pass
    old.write_bytes(pickle.dumps({"results": {key: {"predictions": prediction_of(lanes)}
                                              for key, lanes in frames.items()}}, protocol=0))  # fmt: skip
    with pytest.raises(FormatError) as refused:
        score(old, prepared, bootstrap=0)
    assert str(refused.value) == (
        f"{old}: an OpenLane-V2 submission in pickle protocol 0 or 1: pass --format openlanev2"
    )
    assert score(old, prepared, fmt="openlanev2", bootstrap=0)["frames_predicted"] == 4
    with pytest.raises(FormatError, match="not a file: an OpenLane-V2 submission is one pickle or JSON file"):
        score(tmp_path, prepared, fmt="openlanev2", bootstrap=0)


def test_a_real_log_written_as_openlanev2_scores_its_own_lanes_as_a_perfect_submission(av2_root, tmp_path):
    """The real AV2 val log of ../shared/data in OpenLane-V2's layout (pipeline.synth.openlanev2_writer),
    prepared at OpenLane-V2's 50 x 100 m; its annotated lanes written by write_submission, with distinct
    confidences and links as probabilities, score the paper's metrics at 1 on every frame."""
    from pipeline.synth.openlanev2_writer import write_from_av2

    root, data = tmp_path / "olv2", tmp_path / "prepared"
    written = write_from_av2(av2_root / "val" / "3b3570b4-7b0b-3268-a571-b0889dbf40b6", root, "val")
    prepare("openlanev2", root, data, TargetOptions(bev_range=Range.parse("50x100")))
    frames = predicted(data)
    assert len(frames) == written.frames == 157
    path = tmp_path / "submission.pkl"
    write_submission(path, "the annotation", frames)
    result = score(path, data, bootstrap=0)
    assert (result["frames"], result["frames_predicted"], result["frames_missing"]) == (157, 157, 0)
    assert result["metric_params"]["bev_range"] == "50x100"
    for mode in ("directed", "undirected"):
        assert result[mode]["topo"]["f1"] == result[mode]["junction_topo"]["f1"] == 1.0
    assert result["miou"] == 1.0
