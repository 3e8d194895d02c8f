"""OpenLane-V2 submissions (`--format openlanev2`): the pickle of OpenLane-V2's docs/submission.md,
{"method": ..., "results": {(split, segment_id, timestamp): {"predictions": {"lane_centerline": [{"id",
"points" (k, 3), "confidence"}, ...], "traffic_element", "topology_lclc" (k, k) probabilities,
"topology_lcte"}}}}, and the same structure as JSON: {"results": [{"split", "segment_id", "timestamp",
"predictions"}, ...]} with lists for arrays. `write_submission` writes the pickle (`cli eval` on OpenLane-V2
data). docs/guide/score.md is the user's page; what each step does and why:

- The pickle is read by a restricted unpickler: it rebuilds dicts, lists, tuples, strings, numbers and numpy
  arrays and scalars, and nothing else. Any other global (os.system, a class of the submitter's) is refused in
  one line naming the file and the global, before anything is called; numpy's builders are admitted as
  stand-ins that take only the arguments and states numpy itself writes and build the arrays themselves.
- A frame's lanes become one AnnotatedLanes as the file holds them (OpenLane-V2's ego frame, with heights):
  what `--metric openlanev2` scores. The paper's metrics score its graph: the lanes joined where
  topology_lclc is above 0.5 (pipeline.lane_graph.scored_graph_of_annotated), clipped to the command's
  range, each edge scored by the confidence of its lane. A lane's id is a string or an integer (as
  OpenLane-V2 writes them) of at most LANE_ID_DIGITS digits, kept as text: a pickle holds ints of any length,
  and Python refuses to write out one of more digits than its limit.
- Traffic elements and topology_lcte are not read: DET_t, TOP_lt and OLS are not computed.
- Keys are matched to the prepared frames (pipeline.io.read_openlanev2_keys). A key of no prepared frame is
  refused, the first one named; with `--split`, a key counts when its frame is of that split (or, of no
  frame, when its own split is that one) and the others are ignored. The prepared frames of the split(s)
  scored that the submission lacks are scored as empty predictions.
"""

from __future__ import annotations

import io as bytes_io
import math
import numbers
import pickle
import pickletools
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmark.formats.base import (
    FormatError,
    FramePrediction,
    GroundTruth,
    Options,
    PredictionFormat,
    Predictions,
    Source,
)
from benchmark.formats.result_json import results_list
from pipeline import io
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph, scored_graph_of_annotated
from pipeline.manifest import PreparedData
from pipeline.records import AnnotatedLanes

Key = tuple[str, str, str]  # (split, segment_id, timestamp): a frame's identifier in a submission
NOT_COMPUTED = ("DET_t", "TOP_lt", "OLS")  # the traffic elements' scores: their predictions are not read
KEY_FIELDS = ("split", "segment_id", "timestamp")
KEY_WORDS = "(split, segment_id, timestamp), three strings"
PICKLE_PROTOCOL = 4  # what OpenLane-V2's own io.pickle_dump writes under Python 3.8 to 3.13


# ---- the restricted unpickler -------------------------------------------------------------------------
# A numpy array is pickled as _reconstruct(ndarray, (0,), b"b") then BUILD with (1, shape, dtype, fortran,
# data), its dtype as numpy.dtype(spec, align, copy) then BUILD with (3, byteorder, ...); protocol 5 writes
# _frombuffer(data, dtype, shape, order), a scalar scalar(dtype, data). The stand-ins below take exactly these
# and build the arrays themselves, so that no numpy internals (whose BUILD would take any state, such as a
# dtype's flags) see what the file says.


class Forbidden(Exception):
    """What a submission's pickle asks for that it may not: the words after the file's name."""


class PickleRefusal(FormatError):
    """A pickle refused for what it asks for (a global, a call, a state), before anything of it ran."""


class Guarded:
    """An object the pickle gets from a global: it cannot change it (set, delete) or BUILD it but as the
    subclass allows."""

    __slots__ = ()
    what = "an admitted global"

    def __setattr__(self, key, value):
        raise Forbidden(f"sets {key!r} on {self.what}")

    def __delattr__(self, key):
        raise Forbidden(f"deletes {key!r} of {self.what}")

    def __setstate__(self, state):
        raise Forbidden(f"rebuilds {self.what}")


class Stand(Guarded):
    """The stand-in for one global that a submission's pickle may name: called, it checks that its arguments
    are those numpy writes and builds what numpy would."""

    __slots__ = ("what", "build")

    def __init__(self, what: str, build: Callable) -> None:
        object.__setattr__(self, "what", what)
        object.__setattr__(self, "build", build)

    def __call__(self, *args):
        return self.build(*args)


NUMBERS = "biufc"  # the dtype kinds a submission's arrays and scalars may have: booleans and numbers


class DtypeBuilder(Guarded):
    """numpy.dtype(spec, align, copy) of numbers, its byte order set by the BUILD that follows."""

    __slots__ = ("dtype",)
    what = "numpy.dtype"

    def __init__(self, *args) -> None:
        spec, flags = (args or (None,))[0], args[1:]
        if not isinstance(spec, str) or len(flags) > 2 or not all(isinstance(f, bool) for f in flags):
            raise refuse_call("numpy.dtype", args)
        try:
            made = np.dtype(spec)
        except (TypeError, ValueError) as error:
            raise refuse_call("numpy.dtype", args) from error
        if made.kind not in NUMBERS or made.fields is not None or made.subdtype is not None:
            raise Forbidden(f"builds a numpy.dtype of {spec!r}, not of numbers")
        object.__setattr__(self, "dtype", made)

    def __setstate__(self, state):
        """Only the state numpy writes for this dtype in some byte order."""
        order = state[1] if isinstance(state, tuple) and len(state) > 1 else None
        made = self.dtype.newbyteorder(order) if order in ("<", ">", "|", "=") else None
        if made is None or made.__reduce__()[2] != state:
            raise Forbidden(f"gives numpy.dtype {self.dtype.str!r} a state numpy never writes")
        object.__setattr__(self, "dtype", made)


class ArrayBuilder(Guarded):
    """numpy's _reconstruct(ndarray, (0,), b"b"): an empty array that the BUILD that follows fills."""

    __slots__ = ("array",)
    what = "a numpy array"

    def __init__(self, *args) -> None:
        if len(args) != 3 or args[0] is not NDARRAY or args[1] != (0,) or args[2] != b"b":
            raise refuse_call("numpy's _reconstruct", args)
        object.__setattr__(self, "array", np.zeros(0, np.int8))

    def __setstate__(self, state):
        """(1, shape, dtype, fortran, data): data of exactly the shape's size, as numpy writes it."""
        if not isinstance(state, tuple) or len(state) != 5 or state[0] != 1:
            raise Forbidden("gives a numpy array a state numpy never writes")
        _, shape, kind, fortran, data = state
        order = "F" if fortran is True else "C"
        array = array_of(data, kind, shape, order, "a numpy array's state")
        object.__setattr__(self, "array", array)


def refuse_call(name: str, args: tuple) -> Forbidden:
    shown = ", ".join(arg.what if isinstance(arg, Guarded) else type(arg).__name__ for arg in args)
    return Forbidden(f"calls {name} with arguments numpy never writes ({shown})")


def array_of(data, kind, shape, order: str, what: str) -> np.ndarray:
    """A writable array of numbers from the bytes of a pickle: their size that of the shape."""
    if not isinstance(data, bytes | bytearray) or not isinstance(kind, DtypeBuilder):
        raise Forbidden(f"gives {what} other than bytes and a numpy.dtype")
    if not isinstance(shape, tuple) or not all(type(n) is int and n >= 0 for n in shape):
        raise Forbidden(f"gives {what} a shape that is not a tuple of sizes")
    if len(data) != math.prod(shape) * kind.dtype.itemsize:
        raise Forbidden(f"gives {what} {len(data)} bytes for shape {shape} of {kind.dtype.str}")
    return np.frombuffer(data, kind.dtype).reshape(shape, order=order).copy(order="K")


def frombuffer(*args) -> np.ndarray:
    """numpy's _frombuffer(data, dtype, shape, order) of pickle protocol 5."""
    if len(args) != 4 or args[3] not in ("C", "F"):
        raise refuse_call("numpy's _frombuffer", args)
    return array_of(args[0], args[1], args[2], args[3], "numpy's _frombuffer")


def scalar(*args):
    """numpy's scalar(dtype, its bytes): one number."""
    if len(args) != 2:
        raise refuse_call("numpy's scalar", args)
    return array_of(args[1], args[0], (), "C", "numpy's scalar")[()]


def latin1(*args) -> bytes:
    """_codecs.encode(text, "latin1"): bytes as pickle protocols 0 to 2 write them."""
    if len(args) != 2 or not isinstance(args[0], str) or args[1] != "latin1":
        raise refuse_call("_codecs.encode", args)
    return args[0].encode("latin1")


def empty_bytes(*args) -> bytes:
    """bytes(): b"" as pickle protocols 0 to 2 write it."""
    if args:
        raise refuse_call("bytes", args)
    return b""


def never_called(*args):
    raise Forbidden("calls numpy.ndarray itself")


NDARRAY = Stand("numpy.ndarray", never_called)  # only ever _reconstruct's first argument


def stands(names: tuple[str, ...], build: Callable) -> dict[tuple[str, str], Stand]:
    """One stand-in under each of a global's module paths (numpy 1's and 2's, Python 2's builtins)."""
    stand = Stand(names[0], build)
    return {tuple(name.rsplit(".", 1)): stand for name in names}


ADMITTED: dict[tuple[str, str], Stand] = {
    ("numpy", "ndarray"): NDARRAY,
    **stands(("numpy.core.multiarray._reconstruct", "numpy._core.multiarray._reconstruct"), ArrayBuilder),
    **stands(("numpy.dtype",), DtypeBuilder),
    **stands(("numpy.core.multiarray.scalar", "numpy._core.multiarray.scalar"), scalar),
    **stands(("numpy.core.numeric._frombuffer", "numpy._core.numeric._frombuffer"), frombuffer),
    **stands(("_codecs.encode",), latin1),
    **stands(("builtins.bytes", "__builtin__.bytes"), empty_bytes),
}


class SubmissionUnpickler(pickle.Unpickler):
    """pickle's reader that finds no global but the stand-ins of ADMITTED."""

    def find_class(self, module: str, name: str):
        stand = ADMITTED.get((module, name))
        if stand is None:
            raise Forbidden(f"names the global {module}.{name}")
        return stand

    def persistent_load(self, pid):
        raise Forbidden("holds a persistent id")


MEMO_OPCODES = ("PUT", "BINPUT", "LONG_BINPUT")


def check_memo_indices(data: bytes) -> None:
    """Refuses a memo index past the opcodes before it, which no pickler writes: pickle's C reader sizes its
    memo to the largest index, so a 9-byte file could make it fill gigabytes. A malformed stream is left to
    pickle's reader, whose words say what is wrong."""
    try:
        for count, (opcode, index, _) in enumerate(pickletools.genops(data)):
            if opcode.name in MEMO_OPCODES and index > count:
                raise Forbidden(f"stores in memo slot {index} after {count} opcodes")
    except ValueError:
        return


class Realised:
    """The loaded value with each builder replaced by what it built (arrays, dtypes), containers rebuilt.
    Each container's items and each array's bytes count every time they are reached: a memo reference
    repeats any part in a few bytes, so a count past the file's size is a structure blown up by references
    (a tree of [x, x] takes 2^n steps), refused before it is walked; a container within itself is refused."""

    def __init__(self, allowance: int) -> None:
        self.left = allowance
        self.open: set[int] = set()

    def spend(self, count: int) -> None:
        self.left -= count
        if self.left < 0:
            raise Forbidden("repeats its parts by reference past the file's size")

    def __call__(self, value):
        if isinstance(value, ArrayBuilder):
            self.spend(value.array.nbytes)
            return value.array
        if isinstance(value, DtypeBuilder):
            return value.dtype
        if isinstance(value, Guarded):
            raise Forbidden(f"holds {value.what} itself")
        if not isinstance(value, dict | list | tuple):
            return value
        if id(value) in self.open:
            raise Forbidden(f"holds a {type(value).__name__} within itself")
        self.spend(1 + len(value))
        self.open.add(id(value))
        if isinstance(value, dict):
            built = {self(k): self(v) for k, v in value.items()}
        else:
            built = type(value)(self(v) for v in value)
        self.open.discard(id(value))
        return built


def load_pickle(path: Path) -> object:
    """The pickle read by SubmissionUnpickler; one line naming the file and what it asks for otherwise."""
    data = Path(path).read_bytes()
    try:
        check_memo_indices(data)
        return Realised(2 * len(data))(SubmissionUnpickler(bytes_io.BytesIO(data)).load())
    except Forbidden as refused:
        raise PickleRefusal(
            f"{path}: a pickle that {refused}, refused: a submission holds only dicts, lists, tuples, "
            "strings, numbers and numpy arrays; nothing in it was run"
        ) from None
    except Exception as error:  # any fault of a malformed stream (pickle's, a container's, memory): one line
        raise FormatError(f"{path}: not a readable pickle ({type(error).__name__}: {error})") from None


# ---- the submission, read ------------------------------------------------------------------------------


@dataclass
class Submission:
    """A submission file read: its method and each frame's predictions as the file holds them (checked
    when the frame is scored)."""

    method: str | None
    predictions: dict[Key, object]


def is_key(key) -> bool:
    return isinstance(key, tuple) and len(key) == 3 and all(isinstance(part, str) for part in key)


def looks_like_submission(data) -> bool:
    """Detection's look at a loaded pickle: a dict whose "results" is a dict keyed by 3-tuples."""
    results = data.get("results") if isinstance(data, dict) else None
    return isinstance(results, dict) and all(isinstance(k, tuple) and len(k) == 3 for k in results)


def submission_of_pickle(data, path: Path) -> Submission:
    """The pickle's submission: {"method", ..., "results": {(split, segment_id, timestamp): {"predictions":
    ...}}}; one line naming the file and the first key that is not one."""
    if not isinstance(data, dict) or not isinstance(data.get("results"), dict):
        raise FormatError(
            f'{path}: not an OpenLane-V2 submission: no "results" dict (docs/submission.md of OpenLane-V2: '
            '{"method": ..., "results": {(split, segment_id, timestamp): {"predictions": ...}}})'
        )
    bad = [key for key in data["results"] if not is_key(key)]
    if bad:
        raise FormatError(f"{path}: results key {bad[0]!r} is not {KEY_WORDS}")
    predictions = {}
    for key, record in data["results"].items():
        if not isinstance(record, dict) or "predictions" not in record:
            raise FormatError(f'{path}: frame {key}: no "predictions" in its record')
        predictions[key] = record["predictions"]
    return Submission(method_of(data, path), predictions)


def submission_of_json(data, path: Path) -> Submission:
    """The JSON form's submission: {"method", ..., "results": [{"split", "segment_id", "timestamp",
    "predictions"}, ...]}; one line naming the file and the first record that is not one."""
    if not isinstance(data, dict) or not isinstance(data.get("results"), list):
        raise FormatError(
            f'{path}: not an OpenLane-V2 submission: no "results" list ({{"results": [{{"split": ..., '
            '"segment_id": ..., "timestamp": ..., "predictions": ...}, ...]}, as the pickle holds them)'
        )
    predictions = {}
    for index, record in enumerate(data["results"]):
        key = tuple(record.get(name) for name in KEY_FIELDS) if isinstance(record, dict) else None
        if key is None or not is_key(key) or "predictions" not in record:
            raise FormatError(
                f'{path}: results[{index}]: not {{"split", "segment_id", "timestamp" (strings), '
                '"predictions"}'
            )
        if key in predictions:
            raise FormatError(f"{path}: results[{index}]: frame {key} appears twice")
        predictions[key] = record["predictions"]
    return Submission(method_of(data, path), predictions)


def method_of(data: dict, path: Path) -> str | None:
    method = data.get("method")
    if method is not None and not isinstance(method, str):
        raise FormatError(f'{path}: "method" is a {type(method).__name__}, not a string')
    if method is not None and not method.isprintable():  # it is printed, and written into report.md's tables
        raise FormatError(f'{path}: "method" {method[:60]!r} is not one line of printable text')
    return method


def lanes_of(predictions, path: Path, key: Key) -> AnnotatedLanes:
    """One frame's lane_centerline and topology_lclc as AnnotatedLanes, as the file holds them; one line
    naming the file, the frame and what is wrong (a shape, a value that is not a finite number)."""
    where = f"{path}: frame {key}"
    if not isinstance(predictions, dict) or not isinstance(predictions.get("lane_centerline"), list):
        raise FormatError(f'{where}: no "lane_centerline" list in its predictions')
    points, ids, confidence = [], [], []
    for index, lane in enumerate(predictions["lane_centerline"]):
        if not isinstance(lane, dict) or not {"id", "points", "confidence"} <= lane.keys():
            raise FormatError(f'{where}: lane_centerline[{index}] is not {{"id", "points", "confidence"}}')
        ids.append(lane_id_text(lane["id"], f"{where}: lane_centerline[{index}]"))
        name = f"{where}: lane {shortened(repr(lane['id']))}"
        points.append(finite_array(lane["points"], f"{name}: points"))
        if points[-1].ndim != 2 or points[-1].shape[1] != 3 or len(points[-1]) < 2:
            raise FormatError(f"{name}: points of shape {points[-1].shape}, not (n, 3) with n >= 2")
        confidence.append(finite_number(lane["confidence"], f"{name}: confidence"))
    repeated = [name for name, count in Counter(ids).items() if count > 1]
    if repeated:
        raise FormatError(f"{where}: lane id {shortened(repr(repeated[0]))} appears twice")
    if "topology_lclc" not in predictions:
        raise FormatError(f'{where}: no "topology_lclc" in its predictions')
    links = finite_array(predictions["topology_lclc"], f"{where}: topology_lclc")
    if links.shape != (len(ids), len(ids)):
        raise FormatError(
            f"{where}: topology_lclc of shape {links.shape}, not ({len(ids)}, {len(ids)}) for its "
            f"{len(ids)} lanes"
        )
    return AnnotatedLanes(points, links, ids, np.array(confidence, np.float64))


# any Python turns an int of this many digits into text: its limit on that (4,300 digits unless set) can be
# set no lower, and a pickle holds ints of any length
LANE_ID_DIGITS = 640
LANE_ID_BOUND = 10**LANE_ID_DIGITS


def lane_id_text(value, what: str) -> str:
    """A lane's id as text (AnnotatedLanes.ids): a string, or an int (Python's or numpy's) of at most
    LANE_ID_DIGITS digits, as OpenLane-V2 writes them; anything else, one line."""
    allowed = f"a string or an integer of at most {LANE_ID_DIGITS} digits"
    if isinstance(value, str):
        return value
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        raise FormatError(f"{what}: id is a {type(value).__name__}, not {allowed}")
    if not -LANE_ID_BOUND < value < LANE_ID_BOUND:
        raise FormatError(f"{what}: id is an integer of more than {LANE_ID_DIGITS} digits, not {allowed}")
    return str(int(value))


def shortened(text: str, most: int = 60) -> str:
    return text if len(text) <= most else text[:most] + "..."


def finite_array(value, what: str) -> np.ndarray:
    """float64 of an array or nested lists of real numbers (or booleans), every one finite: complex numbers,
    whose imaginary part a cast drops, and strings, which it parses, are refused."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):
        raise FormatError(f"{what}: not an array of numbers") from None
    if array.dtype.kind not in "biuf":
        raise FormatError(f"{what}: not an array of real numbers (numpy reads it as {array.dtype})")
    array = array.astype(np.float64)
    if not np.isfinite(array).all():
        raise FormatError(f"{what}: not an array of finite numbers")
    return array


def finite_number(value, what: str) -> float:
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise FormatError(f"{what}: {shortened(repr(value))} is not a finite number")
    try:
        number = float(value)
    except OverflowError:  # an int of more digits than a float holds: JSON and pickles hold any
        raise FormatError(f"{what}: an integer past a float's range is not a finite number") from None
    if not math.isfinite(number):
        raise FormatError(f"{what}: {value!r} is not a finite number")
    return number


def read_submission(source: Source, keep: bool = False) -> Submission:
    """The file as a submission: a pickle or the JSON form, told by the content (a pickle of protocol 0 or
    1, which has no mark of its own, by its name)."""
    if not source.path.is_file():
        raise FormatError(f"{source.path}: not a file: an OpenLane-V2 submission is one pickle or JSON file")
    if is_pickle(source):
        return submission_of_pickle(source.unpickled(load_pickle, keep), source.path)
    try:
        data = source.json(keep)
    except (ValueError, UnicodeDecodeError) as error:
        raise FormatError(f"{source.path}: neither a pickle nor JSON ({error})") from None
    return submission_of_json(data, source.path)


def is_pickle(source: Source) -> bool:
    """A pickle by its first byte (protocols 2 to 5), or by its name where it is not JSON."""
    if source.head(1) == b"\x80":
        return True
    if not source.is_pickle():
        return False
    try:
        source.json()
    except (ValueError, UnicodeDecodeError):
        return True
    return False


# ---- the format --------------------------------------------------------------------------------------


def detect(source: Source) -> bool:
    """A pickle whose "results" is a dict keyed by 3-tuples, or one that asks for what the restricted reader
    refuses (the reader's line says what); or a JSON file whose results list holds records with
    "predictions"."""
    if source.head(1) == b"\x80":  # pickle protocols 2 to 5
        try:
            return looks_like_submission(source.unpickled(load_pickle))
        except PickleRefusal:
            return True
        except FormatError:
            return False
    records = results_list(source)
    return bool(records) and all(isinstance(r, dict) and "predictions" in r for r in records)


def undecided(source: Source) -> str | None:
    """The line refusing, under auto, a pickle that no format reads (None: not a pickle)."""
    if not source.path.is_file() or not is_pickle(source):
        return None
    try:
        submission_of_pickle(source.unpickled(load_pickle), source.path)
    except FormatError as refusal:
        return f"{refusal}; other codebases' results are read as JSON (--format maptrv2 or cgnet)"
    return f"{source.path}: an OpenLane-V2 submission in pickle protocol 0 or 1: pass --format openlanev2"


def check(source: Source, options: Options) -> str | None:
    """None of a result file's options: a submission keeps every lane, each with its confidence."""
    if given := options.given():
        return (
            f"{', '.join(given)}: only for a result file of MapTRv2 / LaneGAP "
            f"or CGNet (--format maptrv2 or cgnet); {source.path} is read as an OpenLane-V2 submission"
        )
    return None


def frames_of_keys(gt: GroundTruth, path: Path) -> dict[Key, str]:
    """{submission key: frame id} of an OpenLane-V2 prepared dataset; one line for other ground truth."""
    data = PreparedData.open(gt.path)
    if not data.has_annotated_lanes:
        kind = data.kind
        what = f"{kind} data" if kind else "not a prepared dataset"
        raise FormatError(
            f"{path}: an OpenLane-V2 submission, scored against OpenLane-V2 frames; the ground truth "
            f"{gt.path} is {what}: pass one that cli prepare --dataset openlanev2 made"
        )
    return {tuple(key): frame_id for frame_id, key in io.read_openlanev2_keys(gt.path).items()}


def scored_keys(keys, frame_of: dict[Key, str], split_of: dict[str, str], gt: GroundTruth,
                path: Path) -> tuple[dict[Key, str], list[str]]:  # fmt: skip
    """({key: frame id} of the keys scored, the splits scored): every key, or with --split those whose frame
    is of it (a key of no frame: whose own split is it); a key of no prepared frame refused, the first named;
    the splits those of the keys' frames, or --split's."""
    if gt.split:
        gt.check_split(split_of)
        counted = [k for k in keys if (split_of.get(frame_of[k]) if k in frame_of else k[0]) == gt.split]
    else:
        counted = list(keys)
    unknown = sorted(key for key in counted if key not in frame_of)
    if unknown:
        more = f" (and {len(unknown) - 1} more)" if len(unknown) > 1 else ""
        raise FormatError(f"{path}: frame {unknown[0]}{more} is not in the ground truth {gt.path}")
    if not counted and not gt.split:
        raise FormatError(f"{path}: no predicted frame; pass --split to score a split's frames as empty")
    splits = [gt.split] if gt.split else sorted({split_of[frame_of[key]] for key in counted})
    return {key: frame_of[key] for key in counted}, splits


def scored_graphs(frames: list[AnnotatedLanes], rng: Range | None) -> list[tuple[LaneGraph, np.ndarray]]:
    """Each frame's graph of its lanes, clipped to `rng`, each edge scored by its lane's confidence."""
    return [scored_graph_of_annotated(lanes, rng) for lanes in frames]


def graphs_of(frames: list[AnnotatedLanes], rng: Range | None,
              workers: int) -> list[tuple[LaneGraph, np.ndarray]]:  # fmt: skip
    """scored_graphs in `workers` processes where the frames are many."""
    if workers <= 1 or len(frames) < 64 * workers:
        return scored_graphs(frames, rng)
    size = -(-len(frames) // (4 * workers))
    chunks = [frames[i : i + size] for i in range(0, len(frames), size)]
    with ProcessPoolExecutor(workers) as pool:
        return [built for part in pool.map(scored_graphs, chunks, [rng] * len(chunks)) for built in part]


def read(source: Source, options: Options, gt: GroundTruth) -> Predictions:
    """The prepared frames of the keys' split(s) (or --split's), each with its predicted lanes and their
    graph; a frame the submission lacks an empty prediction."""
    frame_of = frames_of_keys(gt, source.path)
    submission = read_submission(source)
    split_of = gt.frame_splits() or {}
    scored, splits = scored_keys(submission.predictions, frame_of, split_of, gt, source.path)
    predictions = submission.predictions
    lanes = {frame_id: lanes_of(predictions[key], source.path, key) for key, frame_id in scored.items()}
    frame_ids = sorted(f for f in gt.graphs if split_of.get(f) in splits)
    predicted = [lanes[f] if f in lanes else AnnotatedLanes([], np.zeros((0, 0)), [], np.zeros(0))
                 for f in frame_ids]  # fmt: skip
    built = graphs_of(predicted, gt.rng, gt.workers)
    frames = [FramePrediction(frame_id, graph, scores, frame_lanes)
              for frame_id, (graph, scores), frame_lanes in zip(frame_ids, built, predicted)]  # fmt: skip
    return Predictions(
        frames=frames,
        splits=splits,
        frames_predicted=len(scored),
        frames_missing=sum(f not in lanes for f in frame_ids),
        frames_in_file=len(submission.predictions),
        frames_not_in_file=0,
        format=FORMAT,
        source=source,
        method=submission.method,
        lanes_read=sum(len(frame) for frame in lanes.values()),
        not_computed=NOT_COMPUTED,
    )


FORMAT = PredictionFormat(
    name="openlanev2",
    title="OpenLane-V2 submission",
    modeling="piece",
    external=True,
    detect=detect,
    check=check,
    read=read,
)


# ---- the submission, written ---------------------------------------------------------------------------


def lane_id(text: str) -> int | str:
    """A lane id as OpenLane-V2 writes them, an int, where the string is one's (it reads back the same)."""
    return int(text) if text.lstrip("-").isdigit() and str(int(text)) == text else text


def prediction_of(lanes: AnnotatedLanes) -> dict:
    """One frame's predictions as docs/submission.md holds them: its lanes (a confidence of 1.0 where the
    lanes have none), topology_lclc, and no traffic element."""
    count = len(lanes)
    confidence = np.ones(count) if lanes.confidence is None else np.asarray(lanes.confidence, np.float64)
    centerlines = [
        {"id": lane_id(name), "points": np.asarray(points, np.float64), "confidence": float(score)}
        for name, points, score in zip(lanes.ids, lanes.points, confidence)
    ]
    return {
        "lane_centerline": centerlines,
        "traffic_element": [],
        "topology_lclc": np.asarray(lanes.links, np.float64),
        "topology_lcte": np.zeros((count, 0)),
    }


def write_submission(path: Path, method: str, frames: dict[Key, AnnotatedLanes]) -> None:
    """OpenLane-V2's submission pickle (its docs/submission.md) of each frame's predicted lanes, by key
    (split, segment_id, timestamp), written atomically: only dicts, lists, tuples, strings, numbers and
    numpy arrays, which OpenLane-V2's own evaluation and this module's reader both read. Each frame is
    checked as the reader checks it first (a ValueError naming the frame)."""
    results = {}
    for key in sorted(frames):
        if not is_key(key):
            raise ValueError(f"write_submission: key {key!r} is not {KEY_WORDS}")
        results[key] = {"predictions": prediction_of(frames[key])}
        lanes_of(results[key]["predictions"], Path(path), key)
    payload = {"method": method, "authors": [], "results": results}
    io.write_atomic(Path(path), lambda tmp: tmp.write_bytes(pickle.dumps(payload, protocol=PICKLE_PROTOCOL)))
