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
    sentences = []
    for block in blocks:
        synthetic = "synthetic " if block.synthetic else ""
        scored, where = block.scored, f"On {synthetic}{block.dataset} ({summary_split(block)})"
        unscored = [run.name for run in block.runs if not run.scored]
        if not scored:
            sentences.append(
                f"{where} no run has scores yet ({', '.join(unscored)}: see the reasons in its table)."
            )
            continue
        if len(scored) == 1:
            run = scored[0]
            sentences.append(
                f"{where} the one scored run, {run.name} ({run.method}, {run.modality}), reaches directed "
                f"TOPO F1 {run.f1_text('directed', 'topo')} and directed Junction TOPO F1 "
                f"{run.f1_text('directed', 'junction_topo')}."
            )
        else:
            leads: dict[str, list[str]] = {}
            differences: dict[tuple[int, int], dict | str] = {}
            for mode, metric in F1_COLUMNS:
                ranked = sorted(scored, key=lambda r: -r.score(mode, metric))
                first, second = ranked[0], ranked[1]
                a, b = first.score(mode, metric), second.score(mode, metric)
                name = f"{mode} {'Junction TOPO' if metric == 'junction_topo' else 'TOPO'} F1"
                if a == b:
                    leads.setdefault(f"{first.name} and {second.name} tie", []).append(
                        f"{name} ({percent(a)} %)"
                    )
                    continue
                pair = (id(first), id(second))
                if pair not in differences:
                    differences[pair] = paired_difference(first, second, draws)
                lead, difference = f"{100 * (a - b):+.1f} points", differences[pair]
                if isinstance(difference, str):
                    text = f"{name} ({percent(a)} % vs {percent(b)} %, {lead}; not tested: {difference})"
                    leads.setdefault(f"{first.name} is ahead of {second.name}", []).append(text)
                    continue
                low, high = (100 * v for v in difference[mode][metric])
                interval = f"[{low:+.1f}, {high:+.1f}]"
                if low > 0:
                    text = (f"{name} ({percent(a)} % vs {percent(b)} % for {second.name}, {lead}, 95 % "
                            f"interval of the difference {interval})")  # fmt: skip
                    leads.setdefault(f"{first.name} leads", []).append(text)
                else:
                    text = (f"{name} ({percent(a)} % vs {percent(b)} %: the 95 % interval of the difference, "
                            f"{interval} points, holds 0)")  # fmt: skip
                    leads.setdefault(f"{first.name} is level with {second.name}", []).append(text)
            parts = [f"{who} on {', '.join(items)}" for who, items in leads.items()]
            sentences.append(f"{where} " + "; ".join(parts) + ".")
        for run in scored:
            floor = run.floor_f1("directed", "topo")
            if floor is not None:
                margin = run.score("directed", "topo") - floor
                side = "above" if margin > 0 else "below" if margin < 0 else "level with"
                sentences.append(
                    f"{run.name} is {abs(100 * margin):.1f} points {side} its sensor-blind floor on directed "
                    f"TOPO F1 ({percent(floor)} %)."
                )
        if unscored:
            sentences.append(f"{len(unscored)} run(s) have no scores: {', '.join(unscored)}.")
    return " ".join(sentences)
