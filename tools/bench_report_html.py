"""report.html's frame browser on many frames, a benchmark, not a test: the file's size, the time
`cli report` spends writing the browser's data, and in headless Chromium (Debian's, as
tests/test_report_html.py drives it) the time to the first paint, to the table drawn, and to sort the table
and draw a frame.

The frames are the 20 validation frames of `cli synth`'s tiny AV2 world (4 logs), repeated under distinct
ids to --frames frames, with two runs as tests/test_report_html.py makes them (`shifted`: the ground truth
shifted 0.2 m with edges dropped; `half`: the ground truth on every other frame); the per-frame counts of
each distinct frame are the metric's own. Each distinct frame's drawing (the metric's matching per edge) is
computed once and its time per frame reported; the repeated frames reuse it, so the writer's time for
--frames distinct frames is that time per frame times --frames.

    python -m tools.bench_report_html [--frames 20000] [--browser-frames 20000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.params import MetricParams
from benchmark.report import browser
from benchmark.report.html import page, script_json
from benchmark.score import score_frames
from pipeline import io
from pipeline.lane_graph import LaneGraph

CHROMIUM, DRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")  # Debian's (make chromium)
# headless, and none of Chromium's own connections (updates, sync, first-run fetches): the page is all
CHROMIUM_ARGUMENTS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                      "--window-size=1400,1000", "--disable-background-networking",
                      "--disable-component-update", "--disable-sync", "--no-first-run")  # fmt: skip


def chromium_installed() -> bool:
    return CHROMIUM.is_file() and DRIVER.is_file()


def headless_chromium(logs: bool = False):
    """A selenium driver of Debian's Chromium, headless (never a browser download); `logs`: the page's console
    and network events readable (get_log("browser"), get_log("performance"))."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for argument in CHROMIUM_ARGUMENTS:
        options.add_argument(argument)
    if logs:
        options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    return webdriver.Chrome(service=Service(str(DRIVER)), options=options)


def synthetic_block(folder: Path, frames: int) -> tuple[browser.BrowserBlock, float]:
    """The repeated block, and the seconds per distinct frame of its drawing."""
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    synth(folder / "raw", logs=4, frames_per_log=4, seed=0, sensors=False, worlds=1, val_frames_per_log=20,
          val_frame_period=0.1)  # fmt: skip
    data = folder / "av2"
    prepare("av2", folder / "raw" / "av2" / "sensor", data, TargetOptions())
    rows = io.read_table(data, "frames", columns=["frame_id", "split"]).to_pylist()
    val = sorted(row["frame_id"] for row in rows if row["split"] == "val")
    gt_all = graphs_from_table(read_graph_table(data), data)
    gt = {f: gt_all[f] for f in val}
    shifted = {}
    for i, f in enumerate(val):
        g, keep = gt[f], np.arange(len(gt[f].src)) % (2 + i % 3) != 0
        shifted[f] = LaneGraph(g.x + np.float32(0.2), g.y, g.src[keep], g.dst[keep])
    half = {f: gt[f] if i % 2 else shifted[f] for i, f in enumerate(val)}
    params = MetricParams(bev_range="30x60")
    ids = [f"{val[k % len(val)]}/copy{k // len(val)}" for k in range(frames)]
    source = {f: val[k % len(val)] for k, f in enumerate(ids)}
    runs = []
    for name, graphs in (("shifted", shifted), ("half", half)):
        _, counts = score_frames([(graphs[f], gt[f]) for f in val], params)
        row = dict(zip(val, counts))
        runs.append(browser.BrowserRun(name, {f: row[source[f]] for f in ids},
                                       {f: graphs[source[f]] for f in ids}))  # fmt: skip
    block = browser.BrowserBlock(
        "av2", "val", "av2 · val split", params, {f: gt[source[f]] for f in ids}, runs
    )
    distinct = [browser.BrowserRun("shifted", {}, shifted), browser.BrowserRun("half", {}, half)]
    one = browser.BrowserBlock("av2", "val", "av2 · val split", params, gt, distinct)
    start = time.perf_counter()
    drawings = dict(zip(val, browser.frame_drawings([one], [(0, f) for f in val])))
    per_frame = (time.perf_counter() - start) / len(val)
    # the repeated frames reuse their drawing
    browser.frame_drawings = lambda blocks, frames, workers=1: [drawings[source[f]] for _, f in frames]
    return block, per_frame


def measure_browser(path: Path) -> dict:
    from selenium.webdriver.support.ui import WebDriverWait

    driver = headless_chromium()
    try:
        results = []
        for _ in range(3):
            driver.get(path.absolute().as_uri())
            WebDriverWait(driver, 120).until(
                lambda d: d.find_element("tag name", "body").get_attribute("data-browser")
            )
            # the script runs before the first paint: wait for it
            timing = WebDriverWait(driver, 120).until(lambda d: d.execute_script(
                "const paint = performance.getEntriesByName('first-contentful-paint')[0];"
                "const ready = performance.getEntriesByName('browser-ready')[0];"
                "return paint && ready ? {paint: paint.startTime, ready: ready.startTime} : null;"
            ))  # fmt: skip
            timing["sort"] = driver.execute_script(
                "const th = document.querySelectorAll('#frame-browser table.frames th')[5];"
                "const t = performance.now(); th.click(); return performance.now() - t;"
            )
            timing["frame"] = driver.execute_script(
                "const tr = document.querySelector('#frame-browser tbody tr');"
                "const t = performance.now(); tr.click(); return performance.now() - t;"
            )
            results.append(timing)
        return {key: min(r[key] for r in results) for key in results[0]}
    finally:
        driver.quit()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--browser-frames", type=int, default=20_000)
    args = parser.parse_args()
    for option, value in (("--frames", args.frames), ("--browser-frames", args.browser_frames)):
        if value < 1:
            parser.error(f"{option} must be at least 1, not {value}")
    if not chromium_installed():  # make bench goes on: the other benchmarks measured what they measure
        print(f"bench_report_html: not measured: no Chromium at {CHROMIUM} and {DRIVER} (make chromium)")
        return
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        block, per_frame = synthetic_block(folder, args.frames)
        start = time.perf_counter()
        data = browser.browser_data([block], args.browser_frames, [])
        seconds = time.perf_counter() - start
        path = folder / "report.html"
        path.write_text(page("bench", "<h1>bench</h1>", data), encoding="utf-8")
        size = path.stat().st_size
        drawings = sum(len(d) for d in data["frames"]["drawing"])
        timing = measure_browser(path)
    kept = len(data["frames"]["id"])
    print(f"{args.frames} frames, {kept} in the browser (--browser-frames {args.browser_frames})")
    json_size = len(script_json(data))
    print(
        f"report.html {size / 1e6:.1f} MB (drawings {drawings / 1e6:.1f} MB; JSON {json_size / 1e6:.1f} MB)"
    )
    print(f"writer: drawing {1e3 * per_frame:.1f} ms per distinct frame (2 runs); the data of all frames "
          f"{seconds:.1f} s with each drawing computed once")  # fmt: skip
    print(f"Chromium (best of 3): first contentful paint {timing['paint']:.0f} ms, table drawn "
          f"{timing['ready']:.0f} ms, sort by a column {timing['sort']:.0f} ms, "
          f"draw a frame {timing['frame']:.0f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
