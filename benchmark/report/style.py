"""How a lane graph is drawn, one place for `cli viz` and `cli report`'s figures (matplotlib,
benchmark/report/figures.py) and report.html's frame browser (SVG, benchmark/report/assets/browser.js):
the colours, the arrow in a piece's driving direction, the ego car.

BEV drawings: x right, y forward (up on the page), metres. Plain data, no matplotlib: report.html
receives it as JSON (`as_json`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

# matplotlib's tab10, the colour of each piece in turn (a piece: a chain between junctions)
PIECE_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
                 "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")  # fmt: skip


@dataclass(frozen=True)
class DrawingStyle:
    matched: str = "#2ca02c"  # a vertex or edge with a partner in the metric's matching
    unmatched: str = "#d62728"
    pieces: tuple[str, ...] = PIECE_COLOURS
    background: str = "#f7f7f7"
    # the arrow halfway along each piece: its shaft reaches this far (m) on each side of the middle
    arrow_half_length: float = 0.8
    arrow_head: float = 0.9  # the head's length (m) in the SVG; matplotlib's mutation_scale below
    arrow_head_side: float = 0.45  # the SVG head's half width, as a share of its length
    arrow_mutation_scale: float = 7.0
    # the SVG's stroke widths (m, in the BEV frame; matplotlib's are in points, figures.py)
    svg_edge_width: float = 0.35
    svg_arrow_width: float = 0.25
    svg_ego_edge_width: float = 0.1
    # the ego car at the origin, 1.9 m x 4.6 m, nose towards +y
    ego_outline: tuple[tuple[float, float], ...] = ((-0.95, -2.3), (0.95, -2.3), (0.95, 1.5), (0.0, 2.3),
                                                    (-0.95, 1.5))  # fmt: skip
    ego_fill: str = "#999999"
    ego_edge: str = "#000000"

    def piece(self, index: int) -> str:
        return self.pieces[index % len(self.pieces)]

    def as_json(self) -> dict:
        """What report.html's browser draws with: all but the piece colours (it colours by the matching) and
        matplotlib's arrow size."""
        matplotlib_only = ("pieces", "arrow_mutation_scale")
        return {key: value for key, value in asdict(self).items() if key not in matplotlib_only}


STYLE = DrawingStyle()
