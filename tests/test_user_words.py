"""The docs and scripts speak of the user's own options, never of limits of machinery that is not theirs
(issue 59): a time limit is LIMIT, which the user sets; an output folder is GPU_CHECK_OUT, which they
choose; the interpreter that holds CUDA torch is PYTHON."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# Where the user reads: every doc, script and module of the checkout (CHANGELOG.md's history aside).
WHERE = ("Makefile", "README.md", "cli.py", ".ci", "docs", "tools", "baselines", "pipeline", "benchmark",
         "tests")  # fmt: skip
SUFFIXES = {".py", ".md", ".sh", ".toml", ".yml", ".yaml", ".txt", ""}
# Each phrase as its words, joined by any whitespace when the pattern is built, so that this list does not
# itself read as the prose it keeps out: sizes, fixed seconds and file counts, a fixed interpreter path and
# an image's package list, each said where the user's own option (LIMIT, GPU_CHECK_OUT, PYTHON) belongs.
NOT_THE_USERS = (
    ("64 ?MiB",),
    ("device", "call"),
    ("travel", "to", "the", "machine"),
    ("within", "540 s"),
    (r"\b8", r"files\b"),
    ("takes", "at", "most", r"8\b"),
    ("as", "on", "the", "device"),
    ("/opt/" + "torch",),
    (r"KINDS\.md",),
)


def user_facing_files() -> list[Path]:
    files = []
    for name in WHERE:
        path = REPO / name
        found = [path] if path.is_file() else [f for f in path.rglob("*") if f.is_file()]
        files += [f for f in found if f.suffix in SUFFIXES and "__pycache__" not in f.parts]
    return [f for f in files if f != Path(__file__).resolve()]


def test_the_docs_and_scripts_name_no_limit_that_is_not_the_users():
    files = user_facing_files()
    assert {REPO / "Makefile", REPO / "README.md", REPO / "tools" / "gpu_setup.sh"} <= set(files)
    pattern = re.compile("|".join(r"\s+".join(words) for words in NOT_THE_USERS), re.IGNORECASE)
    found = [
        f"{f.relative_to(REPO)}:{number}: {line.strip()}"
        for f in files
        for number, line in enumerate(f.read_text(errors="replace").splitlines(), 1)
        if pattern.search(line)
    ]
    assert found == []
