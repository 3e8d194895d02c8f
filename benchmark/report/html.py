"""report.html: report.md as one self-contained page (its tables, notes and pictures, the PNGs inline as
data URIs) with the frame browser (benchmark/report/browser.py's data, drawn by assets/browser.js).

One file that opens from the disk: its styles, script, data and pictures are inside it, and its content
security policy (default-src 'none') lets it fetch nothing. The markdown is rendered from the very text of
report.md (markdown-it, CommonMark with tables), so both hold the same numbers.
"""

from __future__ import annotations

import base64
import html
import json
from importlib import resources
from pathlib import Path

from benchmark.report.browser import DEFAULT_FRAMES, browser_blocks, browser_data
from benchmark.report.runs import Block
from pipeline.io import write_atomic

FILE = "report.html"
# nothing from anywhere: only what is inline, and pictures as data URIs
POLICY = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'"
PICTURE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".svg": "image/svg+xml"}


def asset(name: str) -> str:
    """A file of benchmark/report/assets (packaged with the wheel)."""
    return resources.files("benchmark.report").joinpath("assets", name).read_text(encoding="utf-8")


def markdown_html(text: str, folder: Path) -> str:
    """report.md rendered, each picture it links (a file in `folder`) inline as a data URI; a picture
    not found keeps its alternative text and says so."""
    from markdown_it import MarkdownIt

    md = MarkdownIt("commonmark", {"html": False}).enable("table")

    def image(renderer, tokens, index, options, env):
        token = tokens[index]
        source = str(token.attrGet("src") or "")
        file = folder / source
        alt = html.escape(renderer.renderInlineAsText(token.children or [], options, env), quote=True)
        kind = PICTURE_TYPES.get(file.suffix.lower())
        if kind is None or "/" in source.replace("\\", "/") or not file.is_file():
            missing = f"picture {html.escape(source)} not found beside report.md ({alt})"
            return f'<span class="problem">{missing}</span>'
        data = base64.b64encode(file.read_bytes()).decode()
        return f'<img src="data:{kind};base64,{data}" alt="{alt}" title="{html.escape(source)}">'

    md.add_render_rule("image", image)
    return md.render(text)


def script_json(value) -> str:
    """JSON safe inside a <script> element: no "<" that could close it."""
    return json.dumps(value, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")


def page(title: str, report: str, data: dict) -> str:
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="{POLICY}">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{html.escape(title)}</title>
<style>{asset("style.css")}</style>
</head>
<body>
<nav class="top"><a href="#frame-browser">Frame browser</a> · <a href="#report">Tables</a></nav>
<main id="report">
{report}
</main>
<section id="frame-browser">
<h2>Frame browser</h2>
<div class="messages"><noscript><p class="problem">The frame browser needs JavaScript; the tables above
do not.</p></noscript></div>
<div class="controls"></div>
<div class="frame-view"><p class="note">Choose a frame in the table below.</p></div>
<div class="table-area"></div>
</section>
<script type="application/json" id="browser-data">{script_json(data)}</script>
<script>{asset("browser.js")}</script>
</body>
</html>
"""


def write_html(
    markdown: Path,
    blocks: list[Block],
    frames: int = DEFAULT_FRAMES,
    thumbnails: bool = False,
    workers: int = 1,
) -> Path:
    """report.html beside report.md (`markdown`): its content, then the frame browser of the blocks' frames
    (at most `frames` of them; `thumbnails`: each frame's front camera image, small), its drawings made in
    `workers` processes (0: one per core)."""
    shown, notes = browser_blocks(blocks)
    data = browser_data(shown, frames, notes, workers=workers, thumbnails=thumbnails)
    if not shown:
        data["empty"] = (
            "No run here has per-frame results with its ground truth found, so there are no frames to browse."
        )
    text = markdown.read_text()
    path = markdown.parent / FILE
    content = page("Lane-graph report", markdown_html(text, markdown.parent), data)
    write_atomic(path, lambda tmp: tmp.write_text(content, encoding="utf-8"))
    return path
