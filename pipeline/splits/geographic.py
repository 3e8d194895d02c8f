"""Geographic splits (`cli prepare --split-scheme geographic`): frames assigned to train / val / test by
place, in compact groups of map cells with a buffer to training ground (by default wide enough that no val
or test window shares ground with a training window), and a map picture of any split."""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline.geometry import Range
from pipeline.io import write_atomic
from pipeline.splits.leakage import frame_places, is_training, reach

GROUPS_PER_SMALLEST_SPLIT = 4  # a city is cut into about this many groups per share of its smallest split
ORDERS = 16  # seeded orders of a city's groups tried; the one whose kept shares come nearest the targets wins
PASSES = 3  # assignments per order, each correcting the targets for the frames the buffer removed
MAX_HILBERT_ORDER = 31  # 2**31 cells a side: the curve's index still fits an int64
PANEL_INCHES = 5.0  # one city's panel in draw_split_map, square
DPI = 100
LEFT_OUT = "#7f7f7f"  # left-out frames: dark enough to see on the tinted cells
CELL_EDGE = (0.0, 0.0, 0.0, 0.15)
# frames farther apart than this never see a common patch of ground in the default 30 x 60 m window,
# whatever their headings (its diagonal, 67.08 m)
DEFAULT_BUFFER_M = reach(Range())


@dataclass
class GeoSplit:
    split: list[str | None]  # per input frame; None: in the buffer to training ground, left out
    cells: dict[str, np.ndarray]  # per city (M, 3) int64: cell_x, cell_y, index into split_names
    split_names: list[str]  # training splits first, then the others, each by name
    left_out: dict[str, int]  # frames left out per city
    shares: dict[str, float]  # per split its share of the kept frames (all cities)
    city_shares: dict[str, dict[str, float]]  # per city, per split its share of the city's kept frames
    kept: dict[str, int]  # frames kept per city (in a split, not in the buffer)
    parameters: dict  # cell_m, buffer_m, seed, targets, groups per city, splits missing in a city

    def achieved(self) -> dict:
        """What the scheme gave, for manifest.json and the summary: the target shares, the kept shares of
        all cities and of each city (with its kept and left-out frames), and the splits a city lacks."""
        cities = {
            city: {"frames": self.kept[city], "left_out": self.left_out[city], "shares": shares}
            for city, shares in self.city_shares.items()
        }
        return {"targets": self.parameters["targets"], "shares": self.shares, "cities": cities,
                "missing": self.parameters["missing"]}  # fmt: skip


def ordered_splits(names) -> list[str]:
    """Training splits first, then the others; by name within each (independent of the frames' order)."""
    return sorted(set(names), key=lambda name: (not is_training(name), name))


def hilbert_index(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    """Position along the Hilbert curve that fills the 2**order square, of the integer cells (x, y)."""
    n = 1 << order
    x, y = x.astype(np.int64).copy(), y.astype(np.int64).copy()
    d = np.zeros(len(x), dtype=np.int64)
    s = n >> 1
    while s > 0:
        rx = ((x & s) > 0).astype(np.int64)
        ry = ((y & s) > 0).astype(np.int64)
        d += s * s * ((3 * rx) ^ ry)
        flip = (ry == 0) & (rx == 1)  # rotate the quadrant so that the curve runs on
        x[flip], y[flip] = n - 1 - x[flip], n - 1 - y[flip]
        swap = ry == 0
        x[swap], y[swap] = y[swap], x[swap].copy()
        s >>= 1
    return d


def group_cells(cell_xy: np.ndarray, counts: np.ndarray, n_groups: int) -> np.ndarray:
    """Group of each cell: the cells in Hilbert order, cut into runs of about equal frame counts."""
    # Why Hilbert: consecutive cells along the Hilbert curve always share an edge, so a run of it is a
    # compact, connected patch of the city (a Z-order run jumps across the map at each power of two and
    # leaves scattered pieces, whose long borders with training ground the buffer would eat). Cutting the
    # run by frame counts, not cells, gives groups of equal weight, so the greedy below can meet the
    # shares; several groups per split spread each split over the city instead of one blob.
    shifted = cell_xy - cell_xy.min(axis=0)
    order = max(1, int(shifted.max()).bit_length())
    if order > MAX_HILBERT_ORDER:
        raise ValueError(f"a city spans more than 2**{MAX_HILBERT_ORDER} cells a side: cell_m is too small")
    along = np.argsort(hilbert_index(shifted[:, 0], shifted[:, 1], order), kind="stable")
    middle = np.cumsum(counts[along]) - counts[along] / 2.0  # each cell's frames' midpoint along the run
    run = np.minimum((middle * n_groups / counts.sum()).astype(np.int64), n_groups - 1)
    group = np.empty(len(cell_xy), dtype=np.int64)
    group[along] = np.unique(run, return_inverse=True)[1]  # a crowded cell may skip a number: renumber
    return group


def greedy(sizes: np.ndarray, order: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Split of each group: in the given order, each group goes to the split furthest below its target."""
    want = targets * sizes.sum()
    got = np.zeros(len(targets))
    split = np.empty(len(sizes), dtype=np.int64)
    for g in order:
        split[g] = int(np.argmax(want - got))
        got[split[g]] += sizes[g]
    return split


def buffered(xy: np.ndarray, split: np.ndarray, training: np.ndarray, buffer_m: float) -> np.ndarray:
    """Mask of the frames to leave out: non-training frames within buffer_m of a training frame."""
    is_train = training[split]
    drop = np.zeros(len(xy), dtype=bool)
    if is_train.any() and (~is_train).any():
        bound = np.nextafter(buffer_m, np.inf)
        distance = cKDTree(xy[is_train]).query(xy[~is_train], k=1, distance_upper_bound=bound)[0]
        drop[~is_train] = distance <= buffer_m
    return drop


def _city(xy, cell_m, buffer_m, seed, city, targets, training):
    """One city's assignment: (frame split index, left-out mask, cells (M, 3), group count)."""
    cell_of_frame = np.floor(xy / cell_m).astype(np.int64)
    cell_xy, cell_index, counts = np.unique(cell_of_frame, axis=0, return_inverse=True, return_counts=True)
    cell_index = cell_index.reshape(-1)
    n_groups = min(len(cell_xy), max(len(targets), int(np.ceil(GROUPS_PER_SMALLEST_SPLIT / targets.min()))))
    group = group_cells(cell_xy, counts, n_groups)
    sizes = np.bincount(group, weights=counts)
    # the city's own stream from seed: a city's split does not depend on the others or on their order
    rng = np.random.default_rng([seed, zlib.crc32(city.encode())])
    best = None
    for order in [rng.permutation(len(sizes)) for _ in range(ORDERS)]:
        aim = targets.copy()
        for _ in range(PASSES):
            cell_split = greedy(sizes, order, aim)[group]
            frame_split = cell_split[cell_index]
            drop = buffered(xy, frame_split, training, buffer_m)
            kept = np.bincount(frame_split[~drop], minlength=len(targets)).astype(np.float64)
            achieved = kept / max(kept.sum(), 1.0)
            error = float(np.abs(achieved - targets).max())
            if best is None or error < best[0]:
                best = (error, frame_split, drop, cell_split)
            # the buffer eats non-training frames: aim higher for a split that came out short, try again
            aim = aim * np.clip(targets / np.maximum(achieved, 1e-9), 0.5, 2.0)
            aim /= aim.sum()
    _, frame_split, drop, cell_split = best
    return frame_split, drop, np.column_stack([cell_xy, cell_split]).astype(np.int64), len(sizes)


@dataclass
class _Assignment:
    """All cities' assignment: per frame its split index and whether the buffer leaves it out; per city
    its cells (M, 3), frames left out, group count and the splits it lacks (only cities that lack one)."""

    split_of: np.ndarray
    dropped: np.ndarray
    cells: dict[str, np.ndarray]
    left_out: dict[str, int]
    groups: dict[str, int]
    missing: dict[str, list[str]]


def geographic(
    cities: Sequence[str],
    xy: np.ndarray,
    original: Sequence[str],
    cell_m: float = 100.0,
    buffer_m: float = DEFAULT_BUFFER_M,
    seed: int = 0,
) -> GeoSplit:
    """Each frame's split by place. Per city the positions (xy: (N, 2) world x, y in metres) fall into
    square cells of cell_m; the cells are grouped into compact runs of about equal frame counts, and the
    groups go to the original splits (seeded order, greedy by deficit) so that each split's share of the
    city's frames nears its share of the original frames. A non-training frame within buffer_m of a
    training frame of its city is left out (None); training frames are never dropped. With buffer_m at
    least `reach` of the window (the default: the 30 x 60 m window's diagonal) no kept val or test window
    intersects a training window, whatever the headings. A city with too few cells for every split gets
    what the greedy gives (parameters["missing"] names those splits); a split that gets no frame in any
    city is an error (ValueError naming the split, the cities and --geo-cell)."""
    cities = [str(c) for c in cities]
    original = [str(s) for s in original]
    xy = np.asarray(xy, dtype=np.float64)
    _check_frames(cities, xy, original, cell_m, buffer_m)
    names = ordered_splits(original)
    training = _training_of(names)
    index = {name: i for i, name in enumerate(names)}
    original_index = np.array([index[s] for s in original], dtype=np.int64)
    targets = np.bincount(original_index, minlength=len(names)) / len(original)

    city_names, city_of = np.unique(np.array(cities, dtype=object).astype(str), return_inverse=True)
    assigned = _assign(city_names, city_of, xy, names, targets, training, cell_m, buffer_m, seed)
    kept = np.bincount(assigned.split_of[~assigned.dropped], minlength=len(names))
    if empty := [n for i, n in enumerate(names) if kept[i] == 0]:
        raise ValueError(no_frame_for(empty, names, original_index, city_names, city_of, assigned.cells,
                                      cell_m, buffer_m))  # fmt: skip
    shares = {n: float(kept[i] / max(kept.sum(), 1)) for i, n in enumerate(names)}
    city_shares, city_kept = _city_shares(city_names, city_of, assigned, names)
    parameters = {
        "cell_m": float(cell_m),
        "buffer_m": float(buffer_m),
        "seed": int(seed),
        "targets": {n: float(t) for n, t in zip(names, targets)},
        "grouping": "hilbert",
        "groups": assigned.groups,
        "missing": assigned.missing,
    }
    split = [None if d else names[s] for s, d in zip(assigned.split_of.tolist(), assigned.dropped.tolist())]
    left_out = assigned.left_out
    return GeoSplit(split, assigned.cells, names, left_out, shares, city_shares, city_kept, parameters)


def _check_frames(
    cities: list[str], xy: np.ndarray, original: list[str], cell_m: float, buffer_m: float
) -> None:
    """One city, one split and one finite x, y per frame; a positive cell and a buffer of no less than 0."""
    if xy.ndim != 2 or xy.shape[1] != 2 or not len(cities) == len(original) == len(xy):
        raise ValueError(
            f"{len(cities)} cities, {len(original)} splits and positions of shape {xy.shape}: "
            "need one city, one split and one x, y per frame"
        )
    if not np.isfinite(xy).all():
        raise ValueError(f"{int((~np.isfinite(xy).all(axis=1)).sum())} frame positions are not finite")
    if not (np.isfinite(cell_m) and cell_m > 0) or not (np.isfinite(buffer_m) and buffer_m >= 0):
        raise ValueError(f"cell_m must be > 0 and buffer_m >= 0 metres, not {cell_m} and {buffer_m}")


def _training_of(names: list[str]) -> np.ndarray:
    """Which of the ordered split names are training splits; at least two splits, one of them training."""
    if len(names) < 2:
        found = f"only {names[0]!r}" if names else "no frames"
        raise ValueError(f"needs frames of at least two original splits to share out, found {found}")
    training = np.array([is_training(n) for n in names], dtype=bool)
    if not training.any():
        raise ValueError(
            f"needs a training split ('train' or a name ending in '_train') among the original "
            f"splits, found {', '.join(map(repr, names))}"
        )
    return training


def _assign(
    city_names: np.ndarray,
    city_of: np.ndarray,
    xy: np.ndarray,
    names: list[str],
    targets: np.ndarray,
    training: np.ndarray,
    cell_m: float,
    buffer_m: float,
    seed: int,
) -> _Assignment:
    """Each city's frames assigned on their own (`_city`), gathered."""
    assigned = _Assignment(np.zeros(len(xy), dtype=np.int64), np.zeros(len(xy), dtype=bool), {}, {}, {}, {})
    for c, city in enumerate(city_names.tolist()):
        members = np.flatnonzero(city_of == c)
        frame_split, drop, assigned.cells[city], assigned.groups[city] = _city(
            xy[members], cell_m, buffer_m, seed, city, targets, training
        )
        assigned.split_of[members], assigned.dropped[members] = frame_split, drop
        assigned.left_out[city] = int(drop.sum())
        present = set(frame_split[~drop].tolist())
        if absent := [n for i, n in enumerate(names) if i not in present]:
            assigned.missing[city] = absent
    return assigned


def _city_shares(
    city_names: np.ndarray, city_of: np.ndarray, assigned: _Assignment, names: list[str]
) -> tuple[dict[str, dict[str, float]], dict[str, int]]:
    """Per city: each split's share of the city's kept frames, and the number of them."""
    city_shares, city_kept = {}, {}
    for c, city in enumerate(city_names.tolist()):
        here = np.bincount(assigned.split_of[(city_of == c) & ~assigned.dropped], minlength=len(names))
        city_kept[city] = int(here.sum())
        city_shares[city] = {n: float(here[i] / max(here.sum(), 1)) for i, n in enumerate(names)}
    return city_shares, city_kept


def no_frame_for(empty, names, original_index, city_names, city_of, cells, cell_m, buffer_m) -> str:
    """The one line of splits that the scheme leaves without a frame, though the dataset has some: the
    splits, the cities with their frames and cells, and what to change."""
    splits = ", ".join(f"{name!r} ({_count(int((original_index == names.index(name)).sum()), 'frame')} "
                       "in the dataset)" for name in empty)  # fmt: skip
    counts = np.bincount(city_of, minlength=len(city_names))
    cities = ", ".join(
        f"{city} ({_count(int(counts[c]), 'frame')} in {_count(len(cells[city]), 'cell')})"
        for c, city in enumerate(city_names.tolist())
    )
    return (
        f"split {splits} gets no frame: the cities {cities} have too few cells of --geo-cell {cell_m:g} m to "
        f"share out beyond the {buffer_m:.4g} m buffer to training ground; try a smaller --geo-cell (or the "
        "original split scheme)"
    )


def _count(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def _colours(names: list[str]) -> dict[str, tuple]:
    from matplotlib import colormaps

    tab10 = [colormaps["tab10"](i) for i in range(10) if i != 7]  # 7 is the grey of left-out frames
    return {name: tab10[i % len(tab10)] for i, name in enumerate(names)}


def draw_split_map(
    cities: Sequence[str],
    xy: np.ndarray,
    split: Sequence[str | None],
    path: Path,
    cells: dict | None = None,
    cell_m: float | None = None,
) -> None:
    """A PNG at path: one panel per city, each frame a dot in its split's colour (left-out frames grey),
    the cells of `geographic` outlined and faintly filled in their split's colour when given, a legend
    with the frame counts. Serves any split scheme (cells None)."""
    import matplotlib
    import matplotlib.style
    from matplotlib.figure import Figure

    if cells is not None and not (cell_m and cell_m > 0):
        raise ValueError("draw_split_map needs cell_m (> 0) to draw the cells")
    cities = [str(c) for c in cities]
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    split = [None if s is None else str(s) for s in split]
    if not len(cities) == len(split) == len(xy):
        raise ValueError(f"{len(cities)} cities, {len(split)} splits and {len(xy)} positions: not one each")
    names = ordered_splits(s for s in split if s is not None)
    colour = _colours(names)
    city_names = sorted(set(cities)) or ["(no frames)"]
    columns = min(len(city_names), 3)
    rows = -(-len(city_names) // columns)
    city_arr, split_arr = np.array(cities, dtype=object), np.array(split, dtype=object)

    with matplotlib.rc_context():
        matplotlib.style.use("default")
        figure = Figure(figsize=(columns * PANEL_INCHES, rows * PANEL_INCHES), dpi=DPI, layout="constrained")
        axes = figure.subplots(rows, columns, squeeze=False).ravel()
        for ax in axes[len(city_names) :]:
            ax.set_axis_off()
        for ax, city in zip(axes, city_names):
            members = np.flatnonzero(city_arr == city)
            here, where = split_arr[members], xy[members]
            if cells is not None and city in cells:
                _draw_cells(ax, np.asarray(cells[city]).reshape(-1, 3), here, where, float(cell_m), colour)
            _draw_city(ax, city, here, where, names, colour)
        total = ", ".join(f"{n} {sum(s == n for s in split):,}" for n in names)
        dropped = sum(s is None for s in split)
        figure.suptitle(f"frames by split: {total}" + (f", left out {dropped:,}" if dropped else ""))
        write_atomic(Path(path), lambda tmp: figure.savefig(tmp, format="png", dpi=DPI))


def _draw_city(ax, city: str, here: np.ndarray, where: np.ndarray, names: list[str], colour: dict) -> None:
    """One city's panel: its frames (here: their splits, where: their x, y) as dots, titled, with a legend
    of the frame counts per split."""
    tints = [LEFT_OUT if s is None else colour[s] for s in here]
    # kept frames in one shuffled (fixed) order, so that mixed splits look mixed; left-out on top
    left = np.array([s is None for s in here], dtype=bool)
    for chosen, zorder in ((~left, 3), (left, 4)):
        at = np.flatnonzero(chosen)[np.random.default_rng(0).permutation(int(chosen.sum()))]
        if len(at):
            ax.scatter(
                *where[at].T,
                s=5,
                c=[tints[i] for i in at],
                linewidths=0,
                rasterized=True,
                zorder=zorder,
            )
    handles = _legend_handles(here, names, colour)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{city} ({len(here):,} frames)", fontsize=11)
    ax.set_xlabel("x (m)", fontsize=8)
    ax.set_ylabel("y (m)", fontsize=8)
    ax.tick_params(labelsize=7)
    if handles:
        ax.legend(handles=handles, fontsize=8, loc="best", framealpha=0.85)


def _legend_handles(here: np.ndarray, names: list[str], colour: dict) -> list:
    """A legend entry per split with frames here, then the left-out frames: "val: 1,234 frames"."""
    from matplotlib.lines import Line2D

    handles = []
    for name in [*names, None]:
        count = sum(s == name for s in here)
        if count:
            label = f"{'left out' if name is None else name}: {count:,} frames"
            tint = LEFT_OUT if name is None else colour[name]
            handles.append(Line2D([], [], ls="", marker="o", ms=6, color=tint, label=label))
    return handles


def _draw_cells(ax, cells: np.ndarray, here, where, cell_m: float, colour: dict) -> None:
    """The cells outlined faintly, filled in their split's colour; a cell's split index is named by its
    kept frames (an index none of whose frames was kept stays uncoloured)."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle

    frame_cell = np.floor(where / cell_m).astype(np.int64)
    lookup = {(int(x), int(y)): int(s) for x, y, s in cells}
    named = {}
    for (x, y), s in zip(frame_cell.tolist(), here.tolist()):
        if s is not None and (x, y) in lookup:
            named.setdefault(lookup[(x, y)], s)
    faces = [
        (*colour[named[s]][:3], 0.12) if s in named else (0.0, 0.0, 0.0, 0.0) for s in cells[:, 2].tolist()
    ]
    squares = [Rectangle((x * cell_m, y * cell_m), cell_m, cell_m) for x, y in cells[:, :2].tolist()]
    ax.add_collection(
        PatchCollection(squares, facecolors=faces, edgecolors=[CELL_EDGE], linewidths=0.5, zorder=1)
    )


def draw_dataset_splits(
    data: Path, path: Path, cells: dict | None = None, cell_m: float | None = None
) -> None:
    """draw_split_map of every frame of a prepared dataset (its `frames` table), e.g. DATA/splits.png."""
    places = frame_places(data)
    draw_split_map(places.cities, places.xy, places.splits, path, cells=cells, cell_m=cell_m)
