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
NOT_THE_USERS = (
    r"64 ?MiB",  # what a remote call carries
    r"device call",
    r"travel to the machine",
    r"within 540 s",  # a fixed limit, where LIMIT is the user's
    r"\b8 files\b",
    r"takes at most 8\b",
    r"as on the device",
    r"/opt/torch",  # one image's interpreter, where PYTHON is the user's
    r"KINDS\.md",
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
    pattern = re.compile("|".join(NOT_THE_USERS), re.IGNORECASE)
    found = [
        f"{f.relative_to(REPO)}:{number}: {line.strip()}"
        for f in files
        for number, line in enumerate(f.read_text(errors="replace").splitlines(), 1)
        if pattern.search(line)
    ]
    assert found == []
