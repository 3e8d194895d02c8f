"""The summary paragraph of report.md, in words from the numbers: per block, which run leads on each F1
and whether the lead holds (the paired bootstrap interval of the difference), and each run's floor margin.

A run "leads" only where the 95 % interval of its difference to the next run (same frames, same draws;
benchmark/metric/bootstrap.py) excludes 0; where it holds 0 the two are "level".
"""

from __future__ import annotations

from benchmark.metric import bootstrap
from benchmark.report.measured_tables import F1_COLUMNS
from benchmark.report.runs import Block, Run, SplitKind, percent


def paired_difference(first: Run, second: Run, draws: int) -> dict | str:
    """{mode: {metric: [low, high]}}: the 95 % interval of first's F1 minus second's from the paired
    bootstrap (same frames, same draws); or why there is none."""
    if draws == 0:
        return "no bootstrap (`--bootstrap 0`)"
    for run in (first, second):
        if run.counts is None:
            return f"{run.name}: {run.no_counts}"
    if first.frame_ids != second.frame_ids:
        return "the two were scored on other frames"
    return bootstrap.paired(first.counts, second.counts, draws)


def summary_split(block: Block) -> str:
    """A block's split as the summary names it: "val split", "val split of the geographic scheme"."""
    kind = block.data_split.kind
    of = f" of {kind.value}" if kind not in (SplitKind.ORIGINAL, SplitKind.UNKNOWN) else ""
    return f"{block.split or '?'} split{of}"


def summary(blocks: list[Block], draws: int = bootstrap.DRAWS) -> str:
    """One paragraph in words, generated from the numbers. A run "leads" only where the paired interval
    of its difference to the next run excludes 0; where it holds 0 the two are "level"."""
    return " ".join(sentence for block in blocks for sentence in _block_sentences(block, draws))


def _block_sentences(block: Block, draws: int) -> list[str]:
    """A block's sentences: who leads on each F1 (or the one scored run's F1), each run's floor margin,
    and the runs without scores."""
    synthetic = "synthetic " if block.synthetic else ""
    scored, where = block.scored, f"On {synthetic}{block.dataset} ({summary_split(block)})"
    unscored = [run.name for run in block.runs if not run.scored]
    if not scored:
        return [f"{where} no run has scores yet ({', '.join(unscored)}: see the reasons in its table)."]
    if len(scored) == 1:
        run = scored[0]
        sentences = [
            f"{where} the one scored run, {run.name} ({run.method}, {run.modality}), reaches directed "
            f"TOPO F1 {run.f1_text('directed', 'topo')} and directed Junction TOPO F1 "
            f"{run.f1_text('directed', 'junction_topo')}."
        ]
    else:
        parts = [f"{who} on {', '.join(items)}" for who, items in _leads(scored, draws).items()]
        sentences = [f"{where} " + "; ".join(parts) + "."]
    sentences += [sentence for run in scored if (sentence := _floor_sentence(run))]
    if unscored:
        sentences.append(f"{len(unscored)} run(s) have no scores: {', '.join(unscored)}.")
    return sentences


def _leads(scored: list[Run], draws: int) -> dict[str, list[str]]:
    """Per F1 column, the first two runs compared, grouped by who is ahead of whom and how ("A leads",
    "A is level with B", "A is ahead of B" where untested, "A and B tie"), in the columns' order."""
    leads: dict[str, list[str]] = {}
    differences: dict[tuple[int, int], dict | str] = {}
    for mode, metric in F1_COLUMNS:
        ranked = sorted(scored, key=lambda r: -r.score(mode, metric))
        first, second = ranked[0], ranked[1]
        a, b = first.score(mode, metric), second.score(mode, metric)
        if a == b:
            tie = f"{_f1_name(mode, metric)} ({percent(a)} %)"
            leads.setdefault(f"{first.name} and {second.name} tie", []).append(tie)
            continue
        pair = (id(first), id(second))
        if pair not in differences:
            differences[pair] = paired_difference(first, second, draws)
        who, text = _lead(first, second, mode, metric, differences[pair])
        leads.setdefault(who, []).append(text)
    return leads


def _f1_name(mode: str, metric: str) -> str:
    """The F1 as the summary names it: "directed TOPO F1", "undirected Junction TOPO F1"."""
    return f"{mode} {'Junction TOPO' if metric == 'junction_topo' else 'TOPO'} F1"


def _lead(first: Run, second: Run, mode: str, metric: str, difference: dict | str) -> tuple[str, str]:
    """How first is ahead of second on one F1, by the paired interval of the difference (or why there is
    none): the group it falls in, and its words."""
    a, b, name = first.score(mode, metric), second.score(mode, metric), _f1_name(mode, metric)
    lead = f"{100 * (a - b):+.1f} points"
    if isinstance(difference, str):
        text = f"{name} ({percent(a)} % vs {percent(b)} %, {lead}; not tested: {difference})"
        return f"{first.name} is ahead of {second.name}", text
    low, high = (100 * v for v in difference[mode][metric])
    interval = f"[{low:+.1f}, {high:+.1f}]"
    if low > 0:
        text = (f"{name} ({percent(a)} % vs {percent(b)} % for {second.name}, {lead}, 95 % "
                f"interval of the difference {interval})")  # fmt: skip
        return f"{first.name} leads", text
    text = (f"{name} ({percent(a)} % vs {percent(b)} %: the 95 % interval of the difference, "
            f"{interval} points, holds 0)")  # fmt: skip
    return f"{first.name} is level with {second.name}", text


def _floor_sentence(run: Run) -> str | None:
    """How far the run is above (or below) its sensor-blind floor on directed TOPO F1; None without one."""
    floor = run.floor_f1("directed", "topo")
    if floor is None:
        return None
    margin = run.score("directed", "topo") - floor
    side = "above" if margin > 0 else "below" if margin < 0 else "level with"
    return (
        f"{run.name} is {abs(100 * margin):.1f} points {side} its sensor-blind floor on directed "
        f"TOPO F1 ({percent(floor)} %)."
    )
