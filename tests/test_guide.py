"""The user guide stays usable: every relative link of README.md and docs/ leads to a file that exists,
every `cli <command>` that a guide page's code block names is a command of the command line, and the README
stays a short page without history."""

from __future__ import annotations

import re
from pathlib import Path

import typer
from typer.testing import CliRunner

from cli import app
from pipeline.manifest import read_manifest
from pipeline.splits.leakage import leakage_line

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "guide"
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.M | re.S)
CLI_COMMAND = re.compile(r"(?:^|[\s$(`;|&])cli ([a-z][a-z_-]*)")
# A commit hash as git abbreviates or spells it: 7-40 hex digits, at least one letter and one digit (so
# that a timestamp or a count is not one).
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
README_MOST_LINES = 220


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def relative_links(page: Path) -> list[str]:
    """The link targets of a Markdown page that point into the repository (no scheme, no bare anchor),
    less their #anchor; code blocks are left out (their brackets are not links)."""
    text = FENCE.sub("", page.read_text())
    targets = [match.group(1) for match in LINK.finditer(text)]
    return [
        target.split("#", 1)[0]
        for target in targets
        if not re.match(r"^[a-z][a-z0-9+.-]*:", target) and not target.startswith("#")
    ]


def test_every_relative_link_resolves():
    broken = [
        f"{page.relative_to(ROOT)}: {target}"
        for page in pages()
        for target in relative_links(page)
        if not (page.parent / target).exists()
    ]
    assert broken == []


def anchors(page: Path) -> set[str]:
    """The #anchors of a page's headings, as GitHub makes them: lower case, punctuation but - and _ dropped,
    each space a hyphen."""
    text = FENCE.sub("", page.read_text())
    headings = re.findall(r"^#+ (.+)$", text, re.M)
    return {re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-") for heading in headings}


def test_every_anchor_into_the_guide_exists():
    """A link to a heading of a guide page (prepare.md#splits-and-leakage) names one that is there."""
    broken = []
    for page in pages():
        for target in LINK.findall(FENCE.sub("", page.read_text())):
            path, _, anchor = target.partition("#")
            into = (page.parent / path).resolve() if path else page
            if anchor and into.parent == GUIDE and anchor not in anchors(into):
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert broken == []


def test_the_link_check_sees_a_broken_link(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("[ok](page.md) [gone](missing.md#part) [web](https://example.org) [here](#top)\n"
                    "```\n[not a link](nowhere.md)\n```\n")  # fmt: skip
    assert relative_links(page) == ["page.md", "missing.md"]
    page.write_text("# Adding to a folder, and `--overwrite`\n## The metric variants: `--metric`\n")
    assert anchors(page) == {"adding-to-a-folder-and---overwrite", "the-metric-variants---metric"}


def guide_commands() -> dict[str, list[str]]:
    """Each guide page's `cli <command>` names, as its code blocks hold them."""
    found = {}
    for page in sorted(GUIDE.glob("*.md")):
        blocks = FENCE.findall(page.read_text())
        found[page.name] = [name for block in blocks for name in CLI_COMMAND.findall(block)]
    return found


def test_the_guide_has_its_pages_and_names_only_real_commands():
    commands = set(typer.main.get_command(app).commands)
    found = guide_commands()
    assert set(found) == {"README.md", "prepare.md", "train.md", "score.md", "report.md"}
    for page in ("prepare.md", "train.md", "score.md", "report.md"):
        assert found[page], f"{page} shows no command"
    unknown = sorted({f"{page}: cli {name}" for page, names in found.items() for name in names
                      if name not in commands})  # fmt: skip
    assert unknown == []
    # the pages between them show every command
    assert commands <= {name for names in found.values() for name in names}


def test_the_index_lists_every_page():
    pages_here = {page.name for page in GUIDE.glob("*.md")} - {"README.md"}
    listed = {target for target in relative_links(GUIDE / "README.md") if "/" not in target}
    assert listed == pages_here == {"prepare.md", "train.md", "score.md", "report.md"}


def quoted_leakage_lines(page: Path) -> list[str]:
    """The leakage lines a page quotes from `cli prepare`'s output, in order."""
    return [line for line in page.read_text().splitlines() if line.startswith("split scheme ")]


def test_prepare_pages_leakage_lines_are_what_prepare_prints(synth_raw, synth_prepared, tmp_path):
    """prepare.md quotes, after its real-data lines, the lines of the test suite's synthetic data (conftest's
    synth_raw, AV2) with the default options and with the geographic scheme, as cli prepare prints them."""
    own = leakage_line(read_manifest(synth_prepared["av2"])["leakage"], "original")
    args = ["prepare", "--dataset", "av2", "--root", str(synth_raw / "av2" / "sensor"),
            "--out", str(tmp_path / "geo"), "--split-scheme", "geographic", "--geo-cell", "50",
            "--geo-seed", "3"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    (geographic,) = [line for line in result.output.splitlines() if line.startswith("split scheme ")]
    quoted = quoted_leakage_lines(GUIDE / "prepare.md")
    assert own in quoted and geographic in quoted
    assert quoted.index(own) < quoted.index(geographic)


def commit_lines(text: str) -> list[str]:
    """The lines of a text that name a commit hash."""
    return [line for line in text.splitlines() if COMMIT.search(line)]


def test_the_readme_is_short_and_names_one_commit():
    """About 200 lines, and one commit hash only: the demo table's line with its date (history lives in
    CHANGELOG.md, docs/BENCHMARKS.md and docs/EXPERIMENTS.md)."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= README_MOST_LINES
    (demo_line,) = commit_lines(text)
    assert re.search(r"\b20\d\d-\d\d-\d\d\b", demo_line) and "commit" in demo_line


def test_the_commit_check_sees_a_hash():
    text = ("Made on 2026-12-05 at commit 1084dc5.\n"
            "Frame av2/5f58e02d-e948-3cb0-ac75-b8b5a16e9a0b/315969629259927000, 780 passed\n"
            "at 9f7fe6f0c8a457f1e2d3c4b5a69788990a1b2c3d\n"
            "a plain line: deadline 12-22 points, 1234567 frames, commit abc1234x\n")  # fmt: skip
    assert commit_lines(text) == text.splitlines()[:3]
