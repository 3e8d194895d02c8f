"""`cli prepare`'s OUT/errors.jsonl (--on-error skip): the records of the frames and logs that failed, each
naming its log and the splits of the shards it concerns, kept across runs into the same OUT."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline import io
from pipeline.errors import DataError
from pipeline.manifest import ERRORS


def earlier_errors(out: Path) -> list[dict]:
    """out/errors.jsonl's records (read before any work, so that a damaged file is said in one line)."""
    path, records = out / ERRORS, []
    if not path.is_file():
        return records
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise DataError(path, "text", f"is not UTF-8 ({error.reason}); mend or delete it") from error
    for number, line in enumerate(text.splitlines(), 1):
        try:
            record = json.loads(line) if line.strip() else None
        except json.JSONDecodeError:
            record = None
        named = isinstance(record, dict) and isinstance(record.get("log"), str)
        splits = record.get("splits", []) if named else None
        named_splits = isinstance(splits, list) and all(isinstance(split, str) for split in splits)
        if line.strip() and not (named and named_splits):
            raise DataError(path, f"line {number}", 'not a JSON record naming its "log"; mend or delete it')
        if record is not None:
            records.append(record)
    return records


class ErrorRecords:
    """out/errors.jsonl, written (atomically) as each log is done, so that an interrupted run keeps the
    records of the logs whose shards it finished, and in job order at the end: the earlier records (read
    before any work) less the splits whose shards this run wrote again (a log that failed as a whole is
    tried again by the next run, and its record was added once per run), then this run's. Records of other
    splits of a log stay (a log may be prepared one --split at a time), as do records from before 0.8.1,
    which name no split. The file is rewritten only when a log brings records or narrows earlier ones."""

    def __init__(self, out: Path, earlier: list[dict]):
        self.out, self.earlier = out, earlier
        self.renewed: dict[str, set[str]] = {}  # log -> the splits of its shards written again
        self.done: dict[str, list[dict]] = {}  # log -> its records
        self.written = (out / ERRORS).read_text(encoding="utf-8") if (out / ERRORS).is_file() else ""

    def log_done(self, log: str, splits: list[str], errors: list[dict]) -> None:
        """A log's shards of `splits` are written, with these records."""
        self.renewed.setdefault(log, set()).update(splits)
        self.done[log] = errors
        if errors or any(record["log"] == log and record.get("splits") for record in self.earlier):
            self.write([e for records in self.done.values() for e in records])

    def finish(self, logs: list[str]) -> None:
        """The file in the logs' order (the executors finish logs in any order)."""
        self.write([e for log in logs for e in self.done.get(log, [])])

    def kept(self) -> list[dict]:
        """The earlier records, each less the splits written again (gone when none is left)."""
        kept = []
        for record in self.earlier:
            if not record.get("splits"):
                kept.append(record)
                continue
            renewed = self.renewed.get(record["log"], set())
            left = [split for split in record["splits"] if split not in renewed]
            if left:
                kept.append({**record, "splits": left})
        return kept

    def write(self, errors: list[dict]) -> None:
        path = self.out / ERRORS
        lines = "".join(json.dumps(e) + "\n" for e in self.kept() + errors)
        if lines == self.written:
            return
        if lines:
            io.write_atomic(path, lambda tmp: tmp.write_text(lines, encoding="utf-8"))
        else:
            path.unlink()
        self.written = lines
