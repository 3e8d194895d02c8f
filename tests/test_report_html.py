"""report.html (benchmark/report/html.py, browser.py, assets/browser.js) opened from the disk in headless
Chromium (Debian's chromium and chromium-driver, `make chromium`), driven by selenium.

The runs, written by hand on the session's small synthetic AV2 split (conftest's `synth_prepared`, 20
validation frames; tests/test_report_external.py's helpers, nothing trained): `shifted`, a run of ours
whose predictions are the ground truth shifted 0.2 m with edges dropped; `half`, the ground truth on every
other frame and `shifted`'s elsewhere; `subset`, an external MapTRv2 file's run holding the last 12 frames.
And `old`, a run folder from before per-frame counts (no frame_counts.parquet), and `older`, one whose
metrics.json lacks a key (an older format).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import urllib.parse
from pathlib import Path

import numpy as np
import pytest
from test_report_external import PARAMS, SUBSET, external_metrics, our_extra, scored_folder

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric import bootstrap
from benchmark.metric.densify import unique_edges
from benchmark.report.browser import frame_scores, keep_frames
from benchmark.report.style import STYLE
from benchmark.report.writer import write_report
from pipeline import io
from pipeline.lane_graph import LaneGraph
from tools.bench_report_html import CHROMIUM, DRIVER, chromium_installed, headless_chromium

# a select's option by its text (the runs' options are numbered in the report's order)
CHOOSE = "const choose = (s, text) => { s.value = [...s.options].find(o => o.text === text).value; };"


@pytest.fixture(scope="module")
def made(synth_prepared, tmp_path_factory) -> dict:
    data = synth_prepared["av2"]
    rows = io.read_table(data, "frames", columns=["frame_id", "split"]).to_pylist()
    val = sorted(row["frame_id"] for row in rows if row["split"] == "val")
    gt_all = graphs_from_table(read_graph_table(data), data)
    gt = {f: gt_all[f] for f in val}
    root = tmp_path_factory.mktemp("report_html")
    runs = root / "runs"
    shifted = {}
    for i, f in enumerate(val):
        g, keep = gt[f], np.arange(len(gt[f].src)) % (2 + i % 3) != 0
        shifted[f] = LaneGraph(g.x + np.float32(0.2), g.y, g.src[keep], g.dst[keep])
    half = {f: gt[f] if i % 2 else shifted[f] for i, f in enumerate(val)}
    for name, graphs in (("shifted", shifted), ("half", half)):
        extra, config = our_extra(data, 1 if name == "shifted" else 2)
        scored_folder(runs / name, graphs, gt, extra)
        (runs / name / "config.json").write_text(json.dumps(config))
        (runs / name / "run.json").write_text(json.dumps({"data": str(data), "world_size": 1}))
        (runs / name / "checkpoint.pt").write_bytes(b"")
    subset = val[-SUBSET:]
    extra = external_metrics(data, "maptrv2", SUBSET, len(val) - SUBSET, points_clipped=0, vectors_read=9,
                             vectors_kept=9)  # fmt: skip
    scored_folder(runs / "subset", {f: gt[f] for f in subset}, {f: gt[f] for f in subset}, extra)
    shutil.copytree(runs / "shifted", root / "old" / "old")
    (root / "old" / "old" / bootstrap.FRAME_COUNTS).unlink()
    shutil.copytree(runs / "shifted", root / "old" / "older")  # a metrics.json of an older format
    metrics = json.loads((root / "old" / "older" / "metrics.json").read_text())
    (root / "old" / "older" / "metrics.json").write_text(
        json.dumps({k: v for k, v in metrics.items() if k != "fps"})
    )
    report = write_report([runs, root / "old"], root / "report", draws=0)
    return {"root": root, "data": data, "report": report, "gt": gt, "val": val, "shifted": shifted,
            "half": half, "subset": subset, "runs": runs}  # fmt: skip


def test_page_is_one_file_with_every_table(made):
    page = made["report"].html.read_text()
    assert made["report"].html == made["report"].path.parent / "report.html"
    assert "default-src 'none'" in page
    assert 'src="data:image/png;base64,' in page
    for picture in made["report"].pictures:  # every picture inline, none linked
        assert f'src="{picture.name}"' not in page
    assert "old: not in the frame browser: no frame_counts.parquet" in page
    assert "older: not in the frame browser: " in page and "metrics.json lacks fps" in page


def test_a_report_without_per_frame_results_says_so(made):
    """Runs without frame_counts.parquet or with an older metrics.json: the page says there is nothing to
    browse, and why for each run, rather than an empty browser."""
    report = write_report([made["root"] / "old"], made["root"] / "report_old", draws=0)
    page = report.html.read_text()
    assert "there are no frames to browse" in page
    assert "old: not in the frame browser: no frame_counts.parquet" in page
    assert "older: not in the frame browser: " in page


def test_frame_scores_pool_as_the_metric():
    """A frame's F1 from its count row: precision sum / n_pred etc.; no junction -> none, not 0."""
    row = np.zeros(16)
    row[:8] = [3.0, 4, 1.5, 3, 0, 0, 0, 0]
    scores = frame_scores(row)
    p, r = 3 / 4, 1.5 / 3
    assert scores.precision == p and scores.recall == r
    assert math.isclose(scores.f1, 2 * p * r / (p + r))
    assert scores.junction_f1 is None
    row[4:8] = [1.0, 2, 0.5, 1]
    assert math.isclose(frame_scores(row).junction_f1, 2 * 0.5 * 0.5 / 1.0)


def test_keep_frames_says_why(made):
    from benchmark.report.browser import browser_blocks

    blocks, _ = browser_blocks(made["report"].blocks)
    everything = keep_frames(blocks, 10_000)
    assert len(everything.frames) == 20 and everything.reasons == ["every evaluated frame"]
    kept = keep_frames(blocks, 9)
    assert len(kept.frames) == 9 and kept.total == 20
    assert all(kept.why[key] for key in kept.frames)
    reasons = {kept.reasons[r] for key in kept.frames for r in kept.why[key]}
    assert any("largest differences" in r for r in reasons) and any("lowest" in r for r in reasons)
    assert keep_frames(blocks, 9) == kept  # seeded


def line(x0: float, y0: float, x1: float, y1: float) -> LaneGraph:
    return LaneGraph(np.array([x0, x1], np.float32), np.array([y0, y1], np.float32), np.array([0], np.int32),
                     np.array([1], np.int32))  # fmt: skip


def test_edge_shares_follow_the_metrics_matching():
    """A 10 m ground-truth edge against a prediction 0.2 m beside it (every point within the 0.45 m radius:
    all paired), 3 m beside it (none) and along its first half (the GT edge half paired)."""
    from benchmark.metric.params import MetricParams
    from benchmark.report.browser import edge_shares
    from benchmark.report.figures import matched_vertices

    params = MetricParams()
    gt = line(0, 0, 0, 10)
    for pred, pred_share, gt_share in ((line(0.2, 0, 0.2, 10), 1.0, 1.0), (line(3, 0, 3, 10), 0.0, 0.0),
                                       (line(0, 0, 0, 5), 1.0, 0.5)):  # fmt: skip
        _, p_ok, _, g_ok = matched_vertices(pred, gt, params)
        assert edge_shares(pred, p_ok, params.step) == pytest.approx([pred_share])
        assert edge_shares(gt, g_ok, params.step) == pytest.approx([gt_share], abs=0.02)


def test_drawings_in_workers_are_the_same(made):
    from benchmark.report.browser import browser_blocks, frame_drawings

    blocks, _ = browser_blocks(made["report"].blocks)
    frames = [(0, f) for f in made["val"]]
    assert frame_drawings(blocks, frames, workers=2) == frame_drawings(blocks, frames, workers=1)


def test_thumbnails_are_each_frames_front_camera(made):
    import base64

    import cv2

    from benchmark.report.browser import THUMBNAIL_WIDTH, front_thumbnails

    thumbs, note = front_thumbnails(made["data"], made["val"][:2])
    assert sorted(thumbs) == made["val"][:2] and note == ""
    for uri in thumbs.values():
        assert uri.startswith("data:image/jpeg;base64,")
        jpeg = np.frombuffer(base64.b64decode(uri.partition(",")[2]), np.uint8)
        assert cv2.imdecode(jpeg, cv2.IMREAD_COLOR).shape[1] == THUMBNAIL_WIDTH


# ---------------------------------------------------------------------------------------------------
# In the browser


@pytest.fixture(scope="module")
def browser():
    if not chromium_installed():
        missing = f"no Chromium at {CHROMIUM} and {DRIVER} (`make chromium` installs Debian's)"
        if os.environ.get("LANEGRAPH_BROWSER_REQUIRED") == "1":  # CI (.ci/run): it must run them
            pytest.fail(f"{missing}, and LANEGRAPH_BROWSER_REQUIRED=1")
        pytest.skip(missing)
    driver = headless_chromium(logs=True)
    yield driver
    driver.quit()


def open_report(driver, path: Path, fragment: str = "") -> None:
    driver.get(path.absolute().as_uri() + fragment)
    driver.get_log("browser")  # the log of this page from here on
    driver.refresh()
    wait_ready(driver)


def wait_ready(driver, seconds: float = 30) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    WebDriverWait(driver, seconds).until(
        lambda d: d.find_element("tag name", "body").get_attribute("data-browser")
    )


def table_rows(driver) -> list[list[str]]:
    return driver.execute_script(
        "return [...document.querySelectorAll('#frame-browser table.frames tbody tr')]"
        ".map(tr => [...tr.cells].map(td => td.textContent));"
    )


def header(driver) -> list[str]:
    return driver.execute_script(
        "return [...document.querySelectorAll('#frame-browser table.frames th')].map(th => th.textContent);"
    )


def test_no_console_error_no_request(browser, made):
    open_report(browser, made["report"].html)
    errors = [e for e in browser.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
    assert errors == []
    requests = []
    for entry in browser.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            requests.append(message["params"]["request"]["url"])
    # the page itself (opened, then reloaded), and nothing else: pictures are data: URIs
    assert {u for u in requests if not u.startswith("data:")} == {made["report"].html.absolute().as_uri()}


def test_every_table_of_report_md(browser, made):
    open_report(browser, made["report"].html)
    tables = browser.execute_script(
        "return [...document.querySelectorAll('#report table')].map(t => [...t.rows].map("
        "r => [...r.cells].map(c => c.textContent.trim())));"
    )
    markdown = made["report"].path.read_text().splitlines()
    expected, table = [], []
    for line in markdown + [""]:
        if line.startswith("|"):
            table.append(
                [cell.strip().replace("**", "").replace("`", "") for cell in line.strip("|").split("|")]
            )
        elif table:
            expected.append([row for row in table if not all(set(c) <= {"-"} for c in row)])
            table = []
    assert len(expected) >= 4
    assert tables == expected


def test_table_sorts_and_filters(browser, made):
    open_report(browser, made["report"].html)
    names = header(browser)
    assert names[:5] == ["frame", "data", "kept because", "junctions", "lane length (m)"]
    rows = table_rows(browser)
    assert len(rows) == 20 and sorted(r[0] for r in rows) == made["val"]
    f1 = names.index("shifted dir TOPO F1")
    junctions = names.index("junctions")
    # per-frame F1 from frame_counts.parquet, as the page shows it
    counts = dict(zip(*bootstrap.read_frame_counts(made["runs"] / "shifted" / bootstrap.FRAME_COUNTS)))
    for row in rows:
        assert row[f1] == f"{100 * frame_scores(counts[row[0]]).f1:.1f}"
        assert row[junctions] == str(int(counts[row[0]][7]))
    # a frame with no junction shows none, and the external run no score where it has no frame
    jf1 = names.index("shifted dir J-TOPO F1")
    assert all(r[jf1] == "none" for r in rows if r[junctions] == "0")
    assert all(r[jf1] not in ("none", "–") for r in rows if r[junctions] != "0")
    assert sum(r[names.index("subset dir TOPO F1")] == "–" for r in rows) == 20 - SUBSET
    # `none` only where the run scored the frame: the external run did not score the first frames
    subset_jf1 = names.index("subset dir J-TOPO F1")
    unscored = [r for r in rows if r[0] not in made["subset"]]
    assert any(r[junctions] == "0" for r in unscored)  # a junction-free frame it did not score
    assert all(r[subset_jf1] == "–" for r in unscored)
    assert all(r[subset_jf1] == "none" for r in rows if r[0] in made["subset"] and r[junctions] == "0")
    th = browser.find_elements("css selector", "#frame-browser table.frames th")
    th[f1].click()
    values = [float(r[f1]) for r in table_rows(browser)]
    assert values == sorted(values)
    th[f1].click()
    values = [float(r[f1]) for r in table_rows(browser)]
    assert values == sorted(values, reverse=True)
    # F1 below a value
    browser.execute_script(
        CHOOSE + "const c = document.querySelector('#frame-browser .controls');"
        "choose(c.querySelector('[name=below-run]'), 'shifted');"
        "const v = c.querySelector('[name=below-value]'); v.value = '60';"
        "v.dispatchEvent(new Event('input'));"
    )
    below = table_rows(browser)
    expected = sorted(f for f in made["val"] if 100 * frame_scores(counts[f]).f1 < 60)
    assert 0 < len(expected) < 20 and sorted(r[0] for r in below) == expected
    # the difference of two runs above a value, with junctions from 1
    half = dict(zip(*bootstrap.read_frame_counts(made["runs"] / "half" / bootstrap.FRAME_COUNTS)))
    browser.execute_script(
        CHOOSE + "const c = document.querySelector('#frame-browser .controls');"
        "c.querySelector('[name=reset]').click();"
        "choose(c.querySelector('[name=diff-a]'), 'half');"
        "choose(c.querySelector('[name=diff-b]'), 'shifted');"
        "const v = c.querySelector('[name=diff-value]'); v.value = '5';"
        "v.dispatchEvent(new Event('input'));"
    )
    gaps = {f: 100 * (frame_scores(half[f]).f1 - frame_scores(counts[f]).f1) for f in made["val"]}
    expected = sorted(f for f in made["val"] if gaps[f] > 5)
    assert 0 < len(expected) < 20
    assert sorted(r[0] for r in table_rows(browser)) == expected


def panels(driver) -> dict[str, int]:
    return driver.execute_script(
        "const out = {}; document.querySelectorAll('#frame-browser .panel').forEach("
        "p => { out[p.dataset.panel] = p.querySelectorAll('svg line.edge').length; }); return out;"
    )


def test_choosing_a_frame_draws_each_run(browser, made, capsys):
    open_report(browser, made["report"].html)
    frame = made["subset"][-1]  # in every run
    row = browser.find_element("css selector", f'#frame-browser tr[data-frame="{frame}"]')
    row.click()
    edges = lambda g: len(unique_edges(g, True))  # noqa: E731
    assert all(len(unique_edges(g, True)) == len(g.src) for g in made["gt"].values())
    drawn = {
        "ground truth": made["gt"],
        "shifted": made["shifted"],
        "half": made["half"],
        "subset": made["gt"],
    }
    assert panels(browser) == {name: edges(graphs[frame]) for name, graphs in drawn.items()}
    # the external run predicted this frame as the ground truth: every edge matched
    assert (
        browser.execute_script(
            "return document.querySelectorAll('[data-panel=subset] line.edge.unmatched').length;"
        )
        == 0
    )
    assert urllib.parse.unquote(browser.execute_script("return location.hash;")) == f"#frame={frame}"
    # arrow keys step through the listed frames
    from selenium.webdriver.common.keys import Keys

    browser.find_element("tag name", "body").send_keys(Keys.ARROW_DOWN)
    listed = [r[0] for r in table_rows(browser)]
    following = listed[listed.index(frame) + 1] if listed.index(frame) + 1 < len(listed) else frame
    assert urllib.parse.unquote(browser.execute_script("return location.hash;")) == f"#frame={following}"
    browser.execute_script("document.querySelector('#frame-browser .frame-view').scrollIntoView();")
    folder = made["root"] / "screenshots"
    folder.mkdir(exist_ok=True)
    shot = folder / "report_html_frame.png"
    browser.save_screenshot(str(shot))
    with capsys.disabled():  # shown without -s
        print(f"\nscreenshot: {shot.absolute()}")
    assert shot.stat().st_size > 10_000


def test_address_opens_the_frame(browser, made):
    frame = made["val"][3]
    open_report(browser, made["report"].html, "#frame=" + urllib.parse.quote(frame, safe=""))
    assert (
        browser.execute_script("return document.querySelector('#frame-browser .frame-view h3').textContent;")
        == frame
    )
    assert set(panels(browser)) == {"ground truth", "shifted", "half", "subset"}
    open_report(browser, made["report"].html, "#frame=" + urllib.parse.quote("av2/nowhere/1", safe=""))
    problems = browser.execute_script(
        "return [...document.querySelectorAll('#frame-browser .problem')].map(p => p.textContent);"
    )
    assert any("av2/nowhere/1" in p and "does not hold" in p for p in problems)
    assert browser.execute_script("return document.querySelectorAll('#frame-browser tbody tr').length;") == 20


# ---------------------------------------------------------------------------------------------------
# The review of issue 62: each finding's test


def page_data(path: Path) -> dict:
    """The browser's data inside a report.html."""
    text = path.read_text()
    start = text.index('<script type="application/json" id="browser-data">')
    body = text[text.index(">", start) + 1 :]
    return json.loads(body[: body.index("</script>")])


def counts_of(made, name: str) -> dict[str, np.ndarray]:
    return dict(zip(*bootstrap.read_frame_counts(made["runs"] / name / bootstrap.FRAME_COUNTS)))


def written_page(folder: Path, blocks: list, notes: list[str] = (), spoil=None) -> Path:
    """A report.html of the frame browser alone, from browser.py's blocks; `spoil` changes its data."""
    from benchmark.report.browser import browser_data
    from benchmark.report.html import page

    data = browser_data(blocks, 3000, list(notes))
    if spoil:
        spoil(data)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "report.html"
    path.write_text(page("test", "<h1>test</h1>", data), encoding="utf-8")
    return path


def test_thumbnails_read_only_the_kept_frames(made, tmp_path, monkeypatch):
    """--thumbnails with --browser-frames 5 of 20: only the 5 kept frames' images are read."""
    from benchmark.report import browser
    from benchmark.report.html import write_html

    asked = []
    real = browser.front_thumbnails

    def spy(data, frames):
        asked.extend(frames)
        return real(data, frames)

    monkeypatch.setattr(browser, "front_thumbnails", spy)
    markdown = tmp_path / "report.md"
    shutil.copy(made["report"].path, markdown)
    data = page_data(write_html(markdown, made["report"].blocks, frames=5, thumbnails=True))
    kept = data["frames"]["id"]
    assert len(kept) == 5 and sorted(asked) == sorted(kept)
    assert all(uri.startswith("data:image/jpeg;base64,") for uri in data["frames"]["thumbnail"])


def test_thumbnails_of_a_manifest_without_root(made, tmp_path):
    """A prepared folder whose manifest.json names no raw root: a note, not a KeyError (the frames' images
    are looked for under the folder itself, as pipeline.manifest.PreparedData.sensor_root has it)."""
    from benchmark.report.browser import front_thumbnails

    data = tmp_path / "av2"
    shutil.copytree(made["data"], data)
    manifest = json.loads((data / "manifest.json").read_text())
    del manifest["root"]
    (data / "manifest.json").write_text(json.dumps(manifest))
    thumbs, note = front_thumbnails(data, made["val"][:2])
    assert thumbs == {}
    assert note == f"2 front camera images are missing under {data} (no thumbnail)"


def test_scores_sent_unrounded_and_notes_without_markdown(made):
    """Per-frame F1 sent at 6 digits (the page rounds once, to 0.1 %), and the notes as plain text: no
    markdown backticks in a page that shows them as text."""
    data = page_data(made["report"].html)
    r = [run["name"] for run in data["runs"]].index("shifted")
    counts = counts_of(made, "shifted")
    expected = [round(frame_scores(counts[f]).f1, 6) for f in data["frames"]["id"]]
    assert data["scores"][r]["f1"] == expected
    assert any(a != round(a, 4) for a in expected)  # the check tells 6 digits from 4
    old = [note for note in data["notes"] if note.startswith("old: ")]
    words = "no frame_counts.parquet (evaluated before per-frame counts: re-run cli eval)."
    assert old == [f"old: not in the frame browser: {words}"]
    assert not any("`" in note for note in data["notes"])
    assert not any("`" in block["label"] for block in data["blocks"])


def test_green_is_half_or_more_unrounded():
    """An edge's share paired goes to the page floored to whole percent, so 49.5 % stays below 50 (red)."""
    from benchmark.report.browser import paired_percent

    shares = np.array([0.0, 0.495, 0.4999, 0.5, 0.999, 1.0, 57 / 100, 29 / 100, 7 / 25])
    # 0.57 * 100 and 0.29 * 100 fall just below 57 and 29 in floats: still 57 and 29
    assert paired_percent(shares).tolist() == [0, 49, 49, 50, 99, 100, 57, 29, 28]


def test_keep_frames_drops_zero_gaps_and_perfect_frames(made):
    """The difference lists hold no frame where the two runs score the same, the lowest-F1 lists no frame
    at 100 %; the random sample fills the rest."""
    from benchmark.report.browser import browser_blocks, f1_column

    blocks, _ = browser_blocks(made["report"].blocks)
    block = blocks[0]
    frames = list(block.gt)
    f1 = {run.name: dict(zip(frames, f1_column(block, run, frames))) for run in block.runs}
    kept = keep_frames(blocks, 18)
    assert len(kept.frames) == 18
    labelled = 0
    for key in kept.frames:
        frame = key[1]
        for reason in (kept.reasons[r] for r in kept.why[key]):
            if reason.startswith("among the largest differences"):
                a, c = reason.rsplit(" between ", 1)[1].split(" and ")
                assert f1[a][frame] != f1[c][frame], (frame, reason)
                labelled += 1
            elif reason.endswith("'s lowest dir TOPO F1"):
                name = reason.removeprefix("among ").removesuffix("'s lowest dir TOPO F1")
                assert f1[name][frame] < 1.0, (frame, reason)
                labelled += 1
    assert labelled > 0
    # subset predicts the ground truth (F1 1 on each of its frames): never among its lowest
    assert all(f1["subset"][f] == 1.0 for f in made["subset"])
    assert not any("subset's lowest" in kept.reasons[r] for key in kept.frames for r in kept.why[key])
    assert any(kept.reasons[r].startswith("a random sample") for key in kept.frames for r in kept.why[key])


def test_keep_frames_differences_only_where_runs_differ(made):
    """Two runs that differ on one frame only: that frame alone is among their largest differences (the
    frames where they score the same were kept as such before)."""
    from benchmark.report.browser import BrowserBlock, BrowserRun

    same, half = counts_of(made, "shifted"), counts_of(made, "half")
    odd = made["val"][1]
    assert frame_scores(same[odd]).f1 != frame_scores(half[odd]).f1
    runs = [BrowserRun("a", same, None), BrowserRun("b", {**same, odd: half[odd]}, None)]
    gt = {f: made["gt"][f] for f in made["val"]}
    kept = keep_frames([BrowserBlock("av2", "val", "av2 · val split", PARAMS, gt, runs)], 9)
    why = {key[1]: [kept.reasons[r] for r in kept.why[key]] for key in kept.frames}
    assert [f for f, reasons in why.items() if any("differences" in r for r in reasons)] == [odd]
    assert len(kept.frames) == 9


def test_report_json_names_report_html(made, tmp_path):
    from typer.testing import CliRunner

    from cli import app

    out = tmp_path / "r"
    args = ["report", "--runs", str(made["root"] / "old"), "--out", str(out), "--bootstrap", "0", "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.splitlines()[0])
    assert summary["html"] == str(out / "report.html") and Path(summary["html"]).is_file()


def test_svg_drawn_in_the_style_sent(browser, made):
    """The SVG's stroke widths and arrow heads come from style.py's DrawingStyle (as cli viz's), and the
    page gets only what it draws with."""
    sent = page_data(made["report"].html)["style"]
    assert "pieces" not in sent and "arrow_mutation_scale" not in sent
    assert sent == json.loads(json.dumps(STYLE.as_json()))
    open_report(browser, made["report"].html)
    browser.find_element("css selector", f'#frame-browser tr[data-frame="{made["val"][0]}"]').click()
    drawn = browser.execute_script(
        "const p = document.querySelector('[data-panel=\"ground truth\"]');"
        "return {edge: p.querySelector('g.edges').getAttribute('stroke-width'),"
        "arrow: p.querySelector('line.arrow').getAttribute('stroke-width'),"
        "ego: p.querySelector('polygon.ego').getAttribute('stroke-width')};"
    )
    assert drawn == {"edge": str(STYLE.svg_edge_width), "arrow": str(STYLE.svg_arrow_width),
                     "ego": str(STYLE.svg_ego_edge_width)}  # fmt: skip


def test_arrow_keys_only_step_a_chosen_frame_on_screen(browser, made):
    """↓ with no frame chosen, with the frame browser scrolled out of sight, or in a filter's input: the page
    keeps its frame and address (it chose row 0 and rewrote the address before)."""
    from selenium.webdriver.common.keys import Keys

    open_report(browser, made["report"].html)
    chosen = "return [location.hash, document.querySelectorAll('#frame-browser tr.chosen').length];"
    body = browser.find_element("tag name", "body")
    browser.execute_script("document.getElementById('frame-browser').scrollIntoView();")
    body.send_keys(Keys.ARROW_DOWN)
    assert browser.execute_script(chosen) == ["", 0]
    frame = made["val"][2]
    browser.find_element("css selector", f'#frame-browser tr[data-frame="{frame}"]').click()
    here = browser.execute_script(chosen)
    assert [urllib.parse.unquote(here[0]), here[1]] == [f"#frame={frame}", 1]
    browser.execute_script("window.scrollTo(0, 0);")
    off = "return document.getElementById('frame-browser').getBoundingClientRect().top > innerHeight;"
    assert browser.execute_script(off)  # the tables of report.md fill the window
    body.send_keys(Keys.ARROW_DOWN)
    assert browser.execute_script(chosen) == here
    field = browser.find_element("css selector", "#frame-browser [name=junctions-max]")
    browser.execute_script("arguments[0].scrollIntoView();", field)
    field.send_keys(Keys.ARROW_LEFT)  # moves the caret; the field's value (and so the list) is unchanged
    assert browser.execute_script(chosen) == here
    assert field.get_attribute("value") == ""
    body.send_keys(Keys.ALT, Keys.ARROW_DOWN)  # with a modifier: the browser's own shortcut, not a step
    assert browser.execute_script(chosen) == here
    body.send_keys(Keys.ARROW_DOWN)  # on screen, a frame chosen: the next listed frame
    assert browser.execute_script(chosen) != here


def browser_run_blocks(made, ids: list[str], drawn_first: bool = True) -> list:
    """One block of browser.py's data over `ids` (frames named after made's first ones)."""
    from benchmark.report.browser import BrowserBlock, BrowserRun

    source = dict(zip(ids, made["val"]))
    counts = counts_of(made, "shifted")
    gt = {f: made["gt"][source[f]] for f in ids}
    row = {f: counts[source[f]] for f in ids}
    shifted = {f: made["shifted"][source[f]] for f in ids}
    runs = [BrowserRun("scores only", row, None), BrowserRun("shifted", row, shifted)]
    return [BrowserBlock("av2", "val", "av2 · val split", PARAMS, gt, runs if drawn_first else runs[::-1])]


def test_a_run_without_predictions_is_not_drawn(browser, made, tmp_path):
    """A run with scores but no predictions.parquet, first in the block: its panel says it is not drawn, and
    the ground truth's edges are coloured by the run that has predictions (all red, '0 found by' before)."""
    path = written_page(tmp_path, browser_run_blocks(made, made["val"][:4]))
    open_report(browser, path)
    frame = made["val"][1]
    browser.find_element("css selector", f'#frame-browser tr[data-frame="{frame}"]').click()
    seen = browser.execute_script(
        "const only = document.querySelector('[data-panel=\"scores only\"]');"
        "const gt = document.querySelector('[data-panel=\"ground truth\"]');"
        "return {svg: only.querySelectorAll('svg').length, text: only.textContent,"
        "options: [...gt.querySelectorAll('select option')].map(o => o.text),"
        "matched: gt.querySelectorAll('line.edge.matched').length,"
        "scores: gt.querySelector('.scores').textContent};"
    )
    assert seen["svg"] == 0 and "not drawn: the run has no predictions.parquet" in seen["text"]
    assert seen["options"] == ["shifted"]
    assert seen["matched"] > 0 and f"{seen['matched']} found by shifted" in seen["scores"]


def test_frame_ids_that_are_object_keys(browser, made, tmp_path):
    """Frame ids "constructor" and "__proto__" in two blocks: the address names the block of the chosen one
    (a plain object's keys counted them wrong, so the link opened the other block's frame)."""
    from benchmark.report.browser import BrowserBlock

    ids = ["constructor", "__proto__"]
    first, second = browser_run_blocks(made, ids), browser_run_blocks(made, ids)
    second = [BrowserBlock("av2", "test", "av2 · test split", PARAMS, second[0].gt, second[0].runs)]
    path = written_page(tmp_path, first + second)
    open_report(browser, path)
    for frame in ids:
        rows = browser.find_elements("css selector", f'#frame-browser tr[data-frame="{frame}"]')
        assert len(rows) == 2
        rows[1].click()
        hash = urllib.parse.unquote(browser.execute_script("return location.hash;"))
        assert hash == f"#frame={frame}&data=1"
    open_report(browser, path, "#frame=constructor&data=1")
    about = "return document.querySelector('#frame-browser .frame-view p.note').textContent;"
    assert browser.execute_script(about).startswith("av2 · test split")


def test_a_failing_browser_says_so(browser, made, tmp_path):
    """Data the script cannot use (here: no runs) stops the frame browser with a line in the page, never a
    blank browser."""
    path = written_page(tmp_path, browser_run_blocks(made, made["val"][:2]), spoil=lambda d: d.pop("runs"))
    browser.get(path.absolute().as_uri())
    wait_ready(browser, 10)
    problems = browser.execute_script(
        "return [...document.querySelectorAll('#frame-browser .problem')].map(p => p.textContent);"
    )
    assert any(p.startswith("The frame browser stopped: ") for p in problems), problems
    assert browser.find_element("tag name", "body").get_attribute("data-browser") == "stopped"


def test_no_frames_to_browse_is_ready(browser, made, tmp_path):
    """The report of runs without per-frame results: the page says why and is ready (it never was)."""
    report = write_report([made["root"] / "old"], tmp_path / "report_old", draws=0)
    browser.get(report.html.absolute().as_uri())
    wait_ready(browser, 10)
    assert browser.find_element("tag name", "body").get_attribute("data-browser") == "ready"
    problems = browser.execute_script(
        "return [...document.querySelectorAll('#frame-browser .problem')].map(p => p.textContent);"
    )
    assert any("there are no frames to browse" in p for p in problems)
