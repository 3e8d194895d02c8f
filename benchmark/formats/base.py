"""What every prediction format's reader is and gives: a `PredictionFormat` record (its name, its detection by
content, its check of the options, its reader), and what a reader gives, one `Predictions`: each scored
frame's `FramePrediction` (the graph, with the scores where the format has them) and the provenance that
the result records. Also what the readers share: the `--pred` file read once (`Source`), the ground truth
they match it to (`GroundTruth`), the frames of a prepared dataset's splits.

Each format is one module of benchmark/formats/ that builds its `PredictionFormat`; benchmark/formats/
__init__.py lists them in one plain tuple and picks the one that reads a file (docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmark.metric.frame import Frame
from pipeline import io
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.records import AnnotatedLanes

SWEEP = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)  # `--sweep`'s kept scores, beside the file's own
PICKLE_SUFFIXES = (".pkl", ".pickle")


class FormatError(ValueError):
    """A prediction file or an option of it that cannot be read; the message names the file or the option."""


@dataclass(frozen=True)
class Options:
    """The options of `--pred` as given (None or False: not given); each format checks the ones it takes."""

    class_name: str | None = None  # the class of vectors scored
    min_score: float | None = None  # the kept score
    sweep: bool = False  # also score at each of SWEEP's kept scores

    def given(self) -> list[str]:
        """The options given, as the command line names them (for a format that takes none of them)."""
        named = (("--class-name", self.class_name), ("--min-score", self.min_score))
        return [name for name, value in named if value is not None] + ["--sweep"] * self.sweep


@dataclass
class Source:
    """`--pred` as given: a file or folder whose content is read at most once, whichever reader asks."""

    given: str  # --pred as the user wrote it
    path: Path
    _parsed: object = field(default=None, repr=False)  # the parsed JSON, or the error parsing it
    _tried: bool = field(default=False, repr=False)
    _unpickled: object = field(default=None, repr=False)  # the pickle as its reader read it, or why not
    _tried_pickle: bool = field(default=False, repr=False)

    @classmethod
    def of(cls, pred_path: Path | str) -> Source:
        return cls(str(pred_path), Path(pred_path))

    def head(self, size: int = 4) -> bytes:
        """The file's first bytes (b"" for a folder or a missing path)."""
        if not self.path.is_file():
            return b""
        with open(self.path, "rb") as file:
            return file.read(size)

    def json(self, keep: bool = True) -> object:
        """The file parsed as JSON, once; a file that is not JSON raises its parse error each time. `keep`
        False: the last asker, after which the parsed file is let go (it can be most of the memory held)."""
        if not self._tried:
            with open(self.path, "rb") as file:  # an OSError is the caller's, never kept
                try:
                    self._parsed = json.load(file)
                except (json.JSONDecodeError, UnicodeDecodeError) as error:
                    self._parsed = error
                except (RecursionError, ValueError) as error:  # too deep, an int of too many digits
                    self._parsed = json.JSONDecodeError("unreadable", "", 0)
                    self._parsed.args = (
                        "arrays or objects nested too deeply to read" if isinstance(error, RecursionError)
                        else str(error),
                    )
            self._tried = True
        parsed = self._parsed
        if not keep:
            self._parsed, self._tried = None, False
        if isinstance(parsed, Exception):
            raise parsed
        return parsed

    def unpickled(self, load: Callable[[Path], object], keep: bool = True) -> object:
        """The file read once by `load`, the one reader of pickles (a restricted one: never pickle.load),
        whose refusal is raised each time; `keep` as for json."""
        if not self._tried_pickle:
            try:
                self._unpickled = load(self.path)
            except FormatError as refusal:
                self._unpickled = refusal
            self._tried_pickle = True
        loaded = self._unpickled
        if not keep:
            self._unpickled, self._tried_pickle = None, False
        if isinstance(loaded, FormatError):
            raise loaded
        return loaded

    def is_pickle(self) -> bool:
        """A pickle by its name or by its first byte (the opcode of protocol 2 and later)."""
        return self.path.is_file() and (
            self.path.suffix.lower() in PICKLE_SUFFIXES or self.head(1) == b"\x80"
        )

    def pickle_refusal(self) -> str | None:
        """A pickle can run code when read: the line that refuses it (None: not a pickle)."""
        if not self.is_pickle():
            return None
        return (
            f"{self.path}: a pickle, refused: reading one can run code. Write the results as JSON in the "
            "schema of MapTRv2's nuscmap_results.json and pass --format maptrv2 or cgnet; an OpenLane-V2 "
            "submission is read with --format openlanev2 (docs/guide/score.md)"
        )

    def refuse_pickle(self) -> None:
        if (refusal := self.pickle_refusal()) is not None:
            raise FormatError(refusal)

    def sha256(self) -> str | None:
        """Of the file (None: a folder)."""
        if not self.path.is_file():
            return None
        digest = hashlib.sha256()
        with open(self.path, "rb") as file:
            for block in iter(lambda: file.read(1 << 20), b""):
                digest.update(block)
        return digest.hexdigest()


@dataclass(frozen=True)
class GroundTruth:
    """What a reader matches the predictions to: the ground truth of `cli score` and its options."""

    path: Path  # --gt: a prepared dataset or a graph-table file
    graphs: dict[str, LaneGraph]  # by frame id
    split: str | None  # --split (None: the split(s) of the predicted frames)
    workers: int  # processes a conversion may use (at least 1)
    rng: Range | None = None  # the command's range, which a format's lanes are clipped to (None: unclipped)

    def frame_splits(self) -> dict[str, str] | None:
        """{frame_id: split} of a prepared dataset's `frames` table; None for a graph-table file."""
        if not (self.path / "frames").is_dir():
            return None
        table = io.read_table(self.path, "frames", columns=["frame_id", "split"])
        return dict(zip(table.column("frame_id").to_pylist(), table.column("split").to_pylist()))

    def check_split(self, split_of: dict[str, str]) -> None:
        """--split names a split of the prepared dataset."""
        if self.split not in set(split_of.values()):
            known = ", ".join(sorted(set(split_of.values())))
            raise FormatError(f"--split {self.split}: no such split in {self.path} (its splits: {known})")


@dataclass(frozen=True)
class FramePrediction:
    """One frame's prediction as a format gives it: its graph and what the format says beyond it."""

    frame_id: str
    graph: LaneGraph
    edge_scores: np.ndarray | None = None  # one per edge of `graph`, its lane's confidence; None: no score
    lanes: AnnotatedLanes | None = None  # an OpenLane-V2 submission's lanes as the file holds them

    def frame(self, gt: LaneGraph, gt_lanes: AnnotatedLanes | None = None,
              ground: tuple[float, float, float] | None = None) -> Frame:  # fmt: skip
        """The frame as the metrics take it, beside its ground truth (with OpenLane-V2 data, the annotated
        lanes and the ground plane)."""
        return Frame(self.graph, gt, self.edge_scores, gt_lanes, self.lanes, ground)


@dataclass(frozen=True)
class Swept:
    """A file converted again at one kept score (`--sweep`)."""

    min_score: float
    vectors_kept: int
    graphs: dict[str, LaneGraph]  # by frame id, the frames scored


@dataclass
class Predictions:
    """A prediction file read and matched to the ground truth's frames: what `cli score` scores, frame by
    frame, and what its result says of the file."""

    frames: list[FramePrediction]  # the frames scored, sorted by id (an empty graph where a file has none)
    splits: list[str] | None  # their split(s); None: a graph-table ground truth, which has none
    frames_predicted: int
    frames_missing: int  # frames of the split(s) without a prediction, scored as empty
    frames_in_file: int
    frames_not_in_file: int  # frames of the split(s) the file lacks, not scored
    format: PredictionFormat
    source: Source
    class_name: str | None = None  # the class of vectors scored (None: the format has no classes)
    min_score: float | None = None  # the kept score (None: the format has no scores to keep by)
    vectors_read: int | None = None  # vectors in the file, every class (None: not a file of vectors)
    vectors_kept: int | None = None  # those of the class above the kept score
    points_clipped: int | None = None  # their points outside the range, clipped
    convert: Callable[[float], Swept] | None = None  # the file at another kept score (None: no scores)
    # an OpenLane-V2 submission: its method, its lanes in the frames scored, the file's scores not computed
    method: str | None = None
    lanes_read: int | None = None
    not_computed: tuple[str, ...] = ()

    def __iter__(self) -> Iterator[FramePrediction]:
        return iter(self.frames)

    @property
    def graphs(self) -> dict[str, LaneGraph]:
        return {prediction.frame_id: prediction.graph for prediction in self.frames}

    def info(self) -> dict:
        """What the result says of the frames scored."""
        return {"splits": self.splits, "frames_predicted": self.frames_predicted,
                "frames_missing": self.frames_missing}  # fmt: skip

    def provenance(self) -> dict:
        """The result's "external": the file, its format and options, what reading it kept."""
        return {
            "format": self.format.name,
            "source": self.source.given,
            "sha256": self.source.sha256(),
            "class_name": self.class_name,
            "min_score": self.min_score,
            "frames_in_file": self.frames_in_file,
            "frames_not_in_file": self.frames_not_in_file,
            "vectors_read": self.vectors_read,
            "vectors_kept": self.vectors_kept,
            "points_clipped": self.points_clipped,
            **({"method": self.method, "lanes_read": self.lanes_read} if self.lanes_read is not None else {}),
            **({"not_computed": list(self.not_computed)} if self.not_computed else {}),
        }

    def sweep(self) -> Iterator[Swept]:
        """The file at each of SWEEP's kept scores and its own, one at a time (`--sweep`)."""
        if self.convert is None or self.min_score is None:
            raise FormatError(
                f"--sweep: only for a result file of another codebase; {self.source.given} is not"
            )
        for min_score in sorted({*SWEEP, self.min_score}):
            yield self.convert(min_score)


@dataclass(frozen=True)
class PredictionFormat:
    """One prediction format: what `--format` calls it and how its files are told, checked and read.

    `detect` looks at the content alone (never the name) and is cheap where it can be: `--format auto`
    asks each format in turn and the first that says yes reads the file. `check` runs before any work and
    gives one line naming the option that this format does not take (None: the options are fine). `read`
    reads the file, matches it to the ground truth and gives the frames to score."""

    name: str  # the --format word, and the result's external.format
    title: str  # what the user reads ("MapTRv2 / LaneGAP JSON")
    modeling: str  # what a file of it predicts: graph, path or piece (a run folder's metrics.json)
    external: bool  # another codebase's file: every result records its provenance (else a run folder's only)
    detect: Callable[[Source], bool]
    check: Callable[[Source, Options], str | None]
    read: Callable[[Source, Options, GroundTruth], Predictions]
