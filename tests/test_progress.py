"""Long work shows a progress bar on a terminal (pipeline/progress.py): `cli score` and `cli roundtrip`
count their frames, work inside other work shows only the outer bar, and off a terminal nothing is drawn."""

from __future__ import annotations

import io

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from rich.console import Console
from typer.testing import CliRunner

from cli import app
from pipeline import progress
from pipeline.io import SCHEMAS


@pytest.fixture
def screen(monkeypatch) -> io.StringIO:
    """A terminal that the bars draw on."""
    out = io.StringIO()
    monkeypatch.setattr(progress, "console", Console(file=out, force_terminal=True, width=100))
    return out


def graph_file(path, frames: int):
    rows = [
        {"frame_id": f"f/{i}", "x": [0.0, 10.0], "y": [0.0, 0.0], "src": [0], "dst": [1]}
        for i in range(frames)
    ]
    pq.write_table(pa.Table.from_pylist(rows, SCHEMAS["graphs"]), path)
    return path


def test_cli_score_counts_its_frames_on_a_terminal(screen, tmp_path):
    gt = graph_file(tmp_path / "gt.parquet", 7)
    result = CliRunner().invoke(app, ["score", "--pred", gt, "--gt", gt, "--bootstrap", 0])
    assert result.exit_code == 0, result.output
    assert "score frames" in screen.getvalue() and "7/7" in screen.getvalue()


def test_inner_work_shows_only_the_outer_bar(screen):
    with progress.track("outer", 2) as advance:
        with progress.track("inner", 5) as inner:
            inner(5)
        advance(2)
    assert "outer" in screen.getvalue() and "inner" not in screen.getvalue()
    assert list(progress.tracked(range(3), "items", 3)) == [0, 1, 2] and "3/3" in screen.getvalue()


def test_nothing_is_drawn_off_a_terminal(monkeypatch):
    out = io.StringIO()
    monkeypatch.setattr(progress, "console", Console(file=out))
    assert list(progress.tracked(range(3), "items", 3)) == [0, 1, 2]
    assert out.getvalue() == ""
