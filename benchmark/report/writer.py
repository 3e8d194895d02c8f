"""`cli report`: write_report assembles DIR/report.md and the PNGs it links from finished runs, and
report.html beside it (the same content in one self-contained page, with a frame browser:
benchmark/report/html.py), and returns what it wrote (Report).

Reads what `cli train` and `cli eval` (RUN/metrics.json, predictions.parquet, config.json, run.json,
log.jsonl, val.jsonl) and `cli roundtrip` (JSON) wrote, and never recomputes a score, with one exception
that says so: the scores by junction count, which score each run's predictions.parquet on subsets of its
frames with the project's own metric. Runs are grouped in blocks, one per prepared dataset and split
(read from the data's manifest.json): runs scored on different frames never share a table.

Each F1 has a 95 % interval from a bootstrap over the block's frames (benchmark/metric/bootstrap.py), drawn
from the per-frame counts `cli eval` keeps (RUN/frame_counts.parquet); the summary calls a run's lead a lead
only when the paired interval of the difference (same frames, same draws) excludes 0. With
`reference="paper"`, the paper's published tables (benchmark/report/reference.py) stand beside the measured
ones they match, as reference tables of their own, and its OpenLane-V2 table in a section of its own beside
the runs on OpenLane-V2 data at its range. Paths are written relative to the working directory.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from benchmark.metric import bootstrap
from benchmark.metric.table import ALWAYS, Metric
from benchmark.report.browser import DEFAULT_FRAMES
from benchmark.report.html import write_html
from benchmark.report.measured_tables import load_roundtrips, roundtrip_tables
from benchmark.report.reference import load_reference
from benchmark.report.runs import Block, group_blocks, load_runs
from benchmark.report.sections import (
    Sections,
    block_sections,
    introduction,
    loss_section,
    openlanev2_section,
    roundtrip_section,
    unplaced_section,
    validation_section,
)
from pipeline.io import write_atomic


@dataclass
class Report:
    path: Path  # report.md
    html: Path  # report.html
    blocks: list[Block]
    pictures: list[Path]
    grids: dict[str, tuple[int, int]]  # picture file name -> (rows, columns) of its panel grid
    # per block (in blocks' order): the paper's tables beside its main table, (heading, header, rows)
    references: list[list[tuple[str, list[str], list[list[str]]]]] = field(default_factory=list)


def write_report(
    runs: list[Path], out: Path, roundtrips: list[Path] = (), workers: int = 1, reference: str | None = None,
    draws: int = bootstrap.DRAWS, metrics: tuple[Metric, ...] = ALWAYS, browser_frames: int = DEFAULT_FRAMES,
    thumbnails: bool = False,
) -> Report:  # fmt: skip
    """Write out/report.md, the PNGs it links and out/report.html; returns what was written.
    `reference="paper"` places the paper's tables beside the measured ones; `draws`: bootstrap draws of the
    intervals (0: none); `metrics` beyond LaneGAP's: a table per other published metric
    (benchmark/report/variant_tables.py); `browser_frames`: the most frames report.html's browser holds;
    `thumbnails`: each browsed frame's front camera image, small."""
    out = Path(out)
    bootstrap.check_draws(draws)
    if browser_frames < 1:
        raise ValueError(f"--browser-frames must be at least 1, not {browser_frames}")
    refs = load_reference(reference) if reference else {}
    blocks = group_blocks(load_runs(runs))
    trip_tables = roundtrip_tables(load_roundtrips(list(roundtrips)))  # checked before anything is written
    for block in blocks:
        for run in block.scored:
            if draws and run.counts is not None:
                run.intervals = bootstrap.intervals(run.counts, draws)
    out.mkdir(parents=True, exist_ok=True)
    doc = Sections(out, refs, workers, metrics=metrics)
    md = introduction(blocks, draws, doc)
    for index, block in enumerate(blocks, 1):
        md += block_sections(index, block, doc)
    md += roundtrip_section(trip_tables, doc)
    md += openlanev2_section(blocks, doc)
    md += unplaced_section(doc)
    md += loss_section(blocks, doc)
    md += validation_section(blocks, doc)
    text = "\n".join(md).rstrip() + "\n"
    path = out / "report.md"
    write_atomic(path, lambda tmp: tmp.write_text(text))
    page = write_html(path, blocks, browser_frames, thumbnails, workers)
    return Report(path, page, blocks, doc.pictures, doc.grids, doc.shown_references)
