"""The lanegraph checkout, for the benchmark and GPU scripts that run from one (make bench, make gpu-check):
they start `cli` there, write relative paths there or read ../shared/data beside it. From an installed copy
(pip install, no checkout around it) they stop with one line that says so."""

from __future__ import annotations

import sys
from pathlib import Path

# the folder that holds pipeline/, baselines/ and benchmark/: the checkout, or site-packages when installed
ROOT = Path(__file__).resolve().parents[1]


def is_checkout() -> bool:
    return (ROOT / "pyproject.toml").is_file() and (ROOT / "Makefile").is_file()


def checkout_root(script: str, how: str) -> Path:
    """The checkout's root; from an installed copy, exit 2 with one line naming `script` and `how` to run it
    from a clone."""
    if not is_checkout():
        print(f"{script} runs from a lanegraph checkout ({how}), not from the installed copy in {ROOT}",
              file=sys.stderr)  # fmt: skip
        raise SystemExit(2)
    return ROOT
