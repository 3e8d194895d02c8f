"""report.html (benchmark/report/html.py) with run folders whose names are markup: a script element, an
element with an event handler, a markdown link to javascript:. The page holds each name as text, never as
markup, and the browser's data holds no "<" that could end its script element."""

from __future__ import annotations

import html
import json
import re
import shutil

from test_report_html import made  # noqa: F401  (the fixture: runs on the synthetic AV2 split)

from benchmark.report.writer import write_report

HOSTILE = ("x<script>alert(3)", "y<img src=q onerror=alert(1)>", "[z](javascript:alert(2))")


def test_run_names_that_are_markup_stay_text(made, tmp_path):  # noqa: F811
    runs = tmp_path / "runs"
    for name in HOSTILE:
        shutil.copytree(made["runs"] / "shifted", runs / name)
    page = write_report([runs], tmp_path / "report", draws=0).html.read_text()
    assert page.count("<script") == 2  # the browser's data and its script, no other
    data = re.search(r'<script type="application/json" id="browser-data">(.*?)</script>', page, re.S)
    assert data and "<" not in data.group(1)
    names = [run["name"] for run in json.loads(data.group(1))["runs"]]
    assert sorted(names) == sorted(HOSTILE)
    assert "<img src=q" not in page and 'href="javascript:' not in page
    assert all(html.escape(name, quote=False) in page for name in HOSTILE)  # in the tables, as text


def test_a_bar_in_a_cell_stays_in_its_cell():
    """A run's or a method's name holding `|` is escaped in report.md's tables, so the row keeps its columns
    (it added a cell before)."""
    from markdown_it import MarkdownIt

    from benchmark.report.measured_tables import markdown_table

    text = markdown_table(["run", "F1"], [["mine | x", "0.5"]])
    assert text.splitlines()[2] == "| mine \\| x | 0.5 |"
    html = MarkdownIt().enable("table").render(text)
    assert html.count("<td>") == 2 and "<td>mine | x</td>" in html
