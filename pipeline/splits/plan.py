"""Which split each frame is prepared into: the dataset's own, split files (log, scene or segment names, or
frames: frame ids, nuScenes sample tokens, AV2 `<log>_<timestamp_ns>`), or the geographic scheme
(geographic.py)."""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import DataError
from pipeline.records import LogIndex

SCHEMES = ("original", "geographic")
# frame lines of a log that is here but that name none of its frames: beyond this many, a format slip (a
# timestamp in microseconds, another dataset's ids) rather than a few frames missing
MAX_UNMATCHED = 5
FRAME_ID = re.compile(r"(?:av2|nuscenes|openlanev2)/([^/\s]+)/(\d+)")
AV2_FRAME = re.compile(r"([0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12})_(\d+)")
SAMPLE_TOKEN = re.compile(r"[0-9a-f]{32}")


@dataclass(frozen=True)
class SplitLine:
    split: str
    path: Path
    number: int
    text: str

    @property
    def frame(self) -> tuple[str, int] | None:
        """(log, timestamp_ns) of a frame id or an AV2 `<log>_<timestamp_ns>` line; None otherwise."""
        match = FRAME_ID.fullmatch(self.text) or AV2_FRAME.fullmatch(self.text)
        return (match[1], int(match[2])) if match else None

    @property
    def is_token(self) -> bool:
        return SAMPLE_TOKEN.fullmatch(self.text) is not None


def check_split_file(split: str, path: Path) -> None:
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: split file of split {split!r} not found")


def split_file_digests(split_files: dict[str, Path]) -> dict[str, str]:
    """{split: sha256 of its file's bytes}: what the manifest records, so that a file edited under the same
    path is told from the one a folder was prepared with."""
    digests = {}
    for split, path in split_files.items():
        check_split_file(split, path)
        digests[split] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return digests


def split_names_digest(path: Path) -> str:
    """sha256 of the names a split file holds (blank lines and # comments left out, as read_split_files
    reads them), sorted and joined by newlines: the same split whatever the order, comments or copy."""
    lines = (line.strip() for line in Path(path).read_text().splitlines())
    names = sorted({line for line in lines if line and not line.startswith("#")})
    return hashlib.sha256("\n".join(names).encode()).hexdigest()


def split_name_digests(split_files: dict[str, Path]) -> dict[str, str]:
    """{split: split_names_digest of its file}: what the manifest records, so that `cli report` can tell
    whose split the data is on (StreamMapNet's) where the files are not (another machine)."""
    for split, path in split_files.items():
        check_split_file(split, path)
    return {split: split_names_digest(path) for split, path in split_files.items()}


def read_split_files(split_files: dict[str, Path]) -> list[SplitLine]:
    """The named lines of one file per split (blank lines and # comments left out), e.g. the geographically
    disjoint splits of StreamMapNet. A line in two files is an error."""
    lines, seen = [], {}
    for split, path in split_files.items():
        check_split_file(split, path)
        for number, line in enumerate(Path(path).read_text().splitlines(), 1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            if seen.get(text, split) != split:
                raise DataError(path, f"line {number}", f"{text} is already in split {seen[text]!r}")
            seen[text] = split
            lines.append(SplitLine(split, Path(path), number, text))
    return lines


def needs_index(lines: list[SplitLine]) -> bool:
    """Whether the files name frames (then every log's frames must be known before preparing)."""
    return any(line.frame or line.is_token for line in lines)


@dataclass
class FilePlan:
    """What split files make of the logs under --root."""

    log_split: dict[str, str] = field(default_factory=dict)  # log -> split of all its frames
    frame_split: dict[str, dict[int, str]] = field(default_factory=dict)  # log -> {timestamp_ns: split}
    elsewhere: int = 0  # lines that name no log under --root (a partial download, another version)
    unmatched: list[SplitLine] = field(default_factory=list)  # frame lines of a log here, no such frame


def plan_from_files(lines: list[SplitLine], logs: list[str], indexes: dict[str, LogIndex]) -> FilePlan:
    """The split of each log named whole and of each frame named alone; `indexes` (log -> LogIndex) when
    the files name frames. A frame both named and in a log named whole, in two splits, is an error."""
    here = set(logs)
    tokens = {
        token: (log, int(t))
        for log, index in indexes.items()
        for token, t in zip(index.sample_tokens or [], index.timestamps)
    }
    times = {log: set(index.timestamps.tolist()) for log, index in indexes.items()}
    plan = FilePlan()
    named: dict[tuple[str, int], SplitLine] = {}
    for line in lines:
        if not (line.frame or line.is_token):  # a log or scene name
            if line.text in here:
                plan.log_split[line.text] = line.split
            else:
                plan.elsewhere += 1
            continue
        frame = line.frame or tokens.get(line.text)
        if frame is None or frame[0] not in here:  # a token of no scene in these tables, a log not here
            plan.elsewhere += 1
        elif frame[1] not in times[frame[0]]:
            plan.unmatched.append(line)
        else:
            named[frame] = line
            plan.frame_split.setdefault(frame[0], {})[frame[1]] = line.split
    for (log, _), line in named.items():
        if plan.log_split.get(log, line.split) != line.split:
            raise DataError(line.path, f"line {line.number}", f"{line.text} is a frame of {log}, which is "
                            f"named whole in split {plan.log_split[log]!r}")  # fmt: skip
    if len(plan.unmatched) > MAX_UNMATCHED:
        first = plan.unmatched[0]
        raise DataError(first.path, f"line {first.number}", f"{first.text} names no frame of its log, nor do "
                        f"{len(plan.unmatched) - 1} more lines (frame ids: <dataset>/<log>/<timestamp_ns>, "
                        "AV2 <log>_<timestamp_ns>, nuScenes sample tokens)")  # fmt: skip
    return plan


def geographic_plan(
    logs: list[str], indexes: dict[str, LogIndex], original: dict[str, str], frame_stride: int,
    cell_m: float, buffer_m: float, seed: int,
) -> tuple[dict[str, dict[int, str | None]], object]:  # fmt: skip
    """{log: {timestamp_ns: split or None (in the buffer)}} of the frames that --frame-stride keeps, by the
    geographic scheme over every log's frames, and the GeoSplit (geographic.py) for the picture and counts."""
    from pipeline.splits.geographic import geographic

    kept = {log: slice(None, None, frame_stride) for log in logs}
    cities = [indexes[log].city for log in logs for _ in indexes[log].timestamps[kept[log]]]
    xy = np.concatenate([indexes[log].xy[kept[log]] for log in logs] or [np.zeros((0, 2))])
    splits = [original[log] for log in logs for _ in indexes[log].timestamps[kept[log]]]
    geo = geographic(cities, xy, splits, cell_m=cell_m, buffer_m=buffer_m, seed=seed)
    plan, start = {}, 0
    for log in logs:
        times = indexes[log].timestamps[kept[log]].tolist()
        plan[log] = dict(zip(times, geo.split[start : start + len(times)]))
        start += len(times)
    return plan, geo
