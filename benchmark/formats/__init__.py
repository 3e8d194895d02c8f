"""The prediction formats that `cli score` reads, one module each, in FORMATS; `choose` picks the one that
reads a `--pred` file: the one named by `--format`, or with `--format auto` (the default) the first whose
detection by content says yes.

Adding a format is one module and one entry: the module builds a `PredictionFormat` (base.py) from its
`detect`, `check` and `read`, and its FORMAT goes into FORMATS below (and `--format`'s choice in cli.py);
docs/ARCHITECTURE.md says more.
"""

from __future__ import annotations

from benchmark.formats import cgnet_json, graph, maptrv2_json, openlanev2_submission, result_json
from benchmark.formats.base import FormatError, Options, PredictionFormat, Source

# in the order `--format auto` asks them; each one's detection excludes the others'
FORMATS: tuple[PredictionFormat, ...] = (
    graph.FORMAT, maptrv2_json.FORMAT, cgnet_json.FORMAT, openlanev2_submission.FORMAT
)
AUTO = "auto"


def choose(source: Source, name: str = AUTO) -> PredictionFormat:
    """The format of `name`, or for `auto` the first of FORMATS that recognises the file's content; one line
    naming the file and the formats tried where none does, or for a result file without vectors (whose
    codebase nothing in it tells) the line asking which."""
    names = [fmt.name for fmt in FORMATS]
    if name != AUTO:
        if name not in names:
            raise FormatError(f"--format {name}: expected one of {', '.join([*names, AUTO])}")
        return FORMATS[names.index(name)]
    if not source.path.exists():
        raise FormatError(f"{source.path}: no such file or folder")
    for fmt in FORMATS:
        if fmt.detect(source):
            return fmt
    if (refusal := openlanev2_submission.undecided(source)) is not None:  # a pickle no format reads
        raise FormatError(refusal)
    if (refusal := result_json.undecided(source)) is not None:
        raise FormatError(refusal)
    tried = ", ".join(fmt.name for fmt in FORMATS)
    raise FormatError(
        f"{source.path}: no format recognises its content (tried {tried}); pass --format NAME to hear why "
        "that one does not read it"
    )


def checked(pred_path, name: str = AUTO, options: Options = Options()) -> tuple[PredictionFormat, Source]:
    """(the format that reads `pred_path`, the file), its options checked, before any work: one line for an
    option the format does not take."""
    source = Source.of(pred_path)
    fmt = choose(source, name)
    error = fmt.check(source, options)
    if error is not None:
        raise FormatError(error)
    return fmt, source
