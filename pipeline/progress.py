"""Progress of long work: a rich bar on stderr while it runs, on a terminal only (logs stay clean).

`with track("score frames", n) as advance:` ... `advance()` once per item, or `for item in
tracked(items, "predict frames", n)`. One bar at a time: work started inside another's (`cli eval`'s
floor search scores each candidate with `score_pairs`, which tracks its frames) shows nothing, and the
outer bar counts.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

console = Console(stderr=True)
_shown: list[Progress] = []  # the bar on screen


def _nothing(n: int = 1) -> None:
    pass


@contextmanager
def track(description: str, total: int) -> Iterator[Callable[..., None]]:
    """Yields `advance(n=1)`; the bar goes away when the work ends."""
    if _shown or not console.is_terminal:
        yield _nothing
        return
    columns = (TextColumn(description), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    bar = Progress(*columns, console=console, transient=True)
    task = bar.add_task(description, total=total)
    _shown.append(bar)
    try:
        with bar:
            yield lambda n=1: bar.advance(task, n)
    finally:
        _shown.pop()


@contextmanager
def holding(bar: Progress) -> Iterator[None]:
    """`bar` (e.g. `cli train`'s) is on screen: work inside it shows no bar of its own (rich shows one
    live display at a time)."""
    _shown.append(bar)
    try:
        yield
    finally:
        _shown.pop()


def tracked(items: Iterable, description: str, total: int) -> Iterator:
    """The items, one step of a `track` bar each."""
    with track(description, total) as advance:
        for item in items:
            yield item
            advance()
