"""Plane curves made of straight lines and circular arcs.

These are the only shapes that both map formats hold exactly: nuScenes stores a lane as arcline
paths (arcs and straights), AV2 as boundary point lists that we can sample as finely as needed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def cross(a: np.ndarray, b: np.ndarray) -> float:
    """z of the cross product of two 2-D vectors (numpy 2 refuses np.cross of 2-D vectors)."""
    return float(a[0] * b[1] - a[1] * b[0])


def wrap_angle(angle: float) -> float:
    """The same angle in [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class Pose:
    x: float
    y: float
    heading: float  # radians, counter-clockwise from +x

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.x, self.y])

    def moved(self, forward: float = 0.0, left: float = 0.0) -> Pose:
        """The pose `forward` metres ahead and `left` metres to the left (negative: right), same heading."""
        c, s = math.cos(self.heading), math.sin(self.heading)
        return Pose(self.x + forward * c - left * s, self.y + forward * s + left * c, self.heading)


@dataclass(frozen=True)
class Piece:
    """A straight line (curvature 0) or a circular arc (curvature 1 / radius, positive turns left)."""

    start: Pose
    curvature: float
    length: float

    def at(self, s: np.ndarray | float) -> np.ndarray:
        """(n, 3) x, y, heading at arc lengths s from the start."""
        s = np.atleast_1d(np.asarray(s, np.float64))
        x0, y0, h0, k = self.start.x, self.start.y, self.start.heading, self.curvature
        heading = h0 + k * s
        if k == 0.0:
            x, y = x0 + s * math.cos(h0), y0 + s * math.sin(h0)
        else:
            x = x0 + (np.sin(heading) - math.sin(h0)) / k
            y = y0 - (np.cos(heading) - math.cos(h0)) / k
        return np.stack([x, y, heading], axis=-1)

    @property
    def end(self) -> Pose:
        x, y, heading = self.at(self.length)[0]
        return Pose(float(x), float(y), float(heading))

    def offset(self, left: float) -> Piece:
        """The parallel curve `left` metres to the left (negative: to the right)."""
        start = self.start.moved(left=left)
        stretch = 1.0 - self.curvature * left  # arcs get shorter on their inside
        if stretch <= 0:
            raise ValueError(f"offset {left} m crosses the centre of an arc of radius {1 / self.curvature} m")
        return Piece(start, self.curvature / stretch, self.length * stretch)

    def reversed(self) -> Piece:
        end = self.end
        return Piece(Pose(end.x, end.y, end.heading + math.pi), -self.curvature, self.length)

    def split(self, parts: int) -> list[Piece]:
        step = self.length / parts
        poses = self.at(np.arange(parts) * step)
        return [Piece(Pose(*map(float, p)), self.curvature, step) for p in poses]

    def intervals(self, spacing: float | None, tolerance: float) -> int:
        """How many chords sample this piece: at most `spacing` long, or (spacing None) the fewest
        whose sagitta stays under `tolerance` (a straight needs one)."""
        if spacing is not None:
            return max(1, math.ceil(self.length / spacing - 1e-9))
        if self.curvature == 0.0:
            return 1
        radius = 1.0 / abs(self.curvature)
        max_angle = 2.0 * math.acos(max(-1.0, 1.0 - tolerance / radius))
        return max(1, math.ceil(self.length / radius / max_angle))


@dataclass(frozen=True)
class Path:
    """Pieces joined end to start, with continuous heading."""

    pieces: tuple[Piece, ...]

    @property
    def length(self) -> float:
        return sum(p.length for p in self.pieces)

    @property
    def start(self) -> Pose:
        return self.pieces[0].start

    @property
    def end(self) -> Pose:
        return self.pieces[-1].end

    def at(self, s: np.ndarray | float) -> np.ndarray:
        """(n, 3) x, y, heading at arc lengths s (clamped to the path)."""
        s = np.clip(np.atleast_1d(np.asarray(s, np.float64)), 0.0, self.length)
        ends = np.cumsum([p.length for p in self.pieces])
        index = np.minimum(np.searchsorted(ends, s, side="left"), len(self.pieces) - 1)
        out = np.empty((len(s), 3))
        for i, piece in enumerate(self.pieces):
            mask = index == i
            if mask.any():
                out[mask] = piece.at(s[mask] - (ends[i] - piece.length))
        return out

    def points(self, spacing: float | None = None, tolerance: float = 0.002) -> np.ndarray:
        """(n, 3) x, y, heading through every piece end; see Piece.intervals for the density."""
        chunks = [self.pieces[0].at(0.0)]
        for piece in self.pieces:
            n = piece.intervals(spacing, tolerance)
            chunks.append(piece.at(np.arange(1, n + 1) * (piece.length / n)))
        return np.concatenate(chunks)

    def offset(self, left: float) -> Path:
        return Path(tuple(p.offset(left) for p in self.pieces))

    def reversed(self) -> Path:
        return Path(tuple(p.reversed() for p in reversed(self.pieces)))


def straight(start: Pose, length: float) -> Piece:
    return Piece(start, 0.0, length)


def arc(start: Pose, radius: float, degrees: float) -> Piece:
    """Turn by `degrees` (positive: left) on a circle of `radius`."""
    return Piece(start, math.copysign(1.0 / radius, degrees), radius * math.radians(abs(degrees)))


def turtle(start: Pose, steps: list[tuple]) -> list[Piece]:
    """Pieces drawn one after the other: ("S", length), ("L", radius, degrees) or ("R", radius, degrees)."""
    pieces, pose = [], start
    for step in steps:
        if step[0] == "S":
            piece = straight(pose, step[1])
        else:
            piece = arc(pose, step[1], step[2] if step[0] == "L" else -step[2])
        pieces.append(piece)
        pose = piece.end
    return pieces


def fillet(a: Pose, b: Pose) -> list[Piece]:
    """Straight, arc, straight from pose a to pose b: the arc is the largest that fits the corner
    where the two heading lines cross (how junction connectors are drawn)."""
    turn = wrap_angle(b.heading - a.heading)
    da = np.array([math.cos(a.heading), math.sin(a.heading)])
    if abs(turn) < 1e-9:
        length = float(np.dot(b.xy - a.xy, da))
        if length <= 0 or abs(cross(da, b.xy - a.xy)) > 1e-6:
            raise ValueError(f"no straight connector from {a} to {b}")
        return [straight(a, length)]
    db = np.array([math.cos(b.heading), math.sin(b.heading)])
    ta, tb = np.linalg.solve(np.column_stack([da, db]), b.xy - a.xy)  # a + ta da = b - tb db
    if ta <= 0 or tb <= 0:
        raise ValueError(f"no fillet connector from {a} to {b}")
    tangent = min(ta, tb)
    radius = tangent / math.tan(abs(turn) / 2)
    pieces = []
    if ta - tangent > 1e-6:
        pieces.append(straight(a, ta - tangent))
    pieces.append(arc(pieces[-1].end if pieces else a, radius, math.degrees(turn)))
    if tb - tangent > 1e-6:
        pieces.append(straight(pieces[-1].end, tb - tangent))
    return pieces


def arc_to(start: Pose, point: np.ndarray) -> Piece:
    """The circular arc (or straight) leaving `start` along its heading and ending at `point`."""
    chord = np.asarray(point, np.float64) - start.xy
    tangent = np.array([math.cos(start.heading), math.sin(start.heading)])
    half_turn = math.atan2(cross(tangent, chord), float(tangent @ chord))
    length = float(np.hypot(*chord))
    if abs(half_turn) < 1e-12:
        return straight(start, length)
    return Piece(start, 2.0 * math.sin(half_turn) / length, length * half_turn / math.sin(half_turn))


def biarc(a: Pose, b: Pose) -> list[Piece]:
    """Two arcs from pose a to pose b with equal tangent lengths: joins any two poses smoothly, where a
    fillet cannot (lanes that shift sideways through a junction, headings whose lines cross behind)."""
    ta = np.array([math.cos(a.heading), math.sin(a.heading)])
    tb = np.array([math.cos(b.heading), math.sin(b.heading)])
    v, t = b.xy - a.xy, ta + tb
    denominator = 2.0 * (1.0 - float(ta @ tb))  # 4 - |t|^2
    if denominator < 1e-12:  # parallel headings: the S-curve's tangent lengths solve a linear equation
        tangent = float(v @ v) / (4.0 * float(v @ ta))
    else:
        vt = float(v @ t)
        tangent = (-vt + math.sqrt(vt * vt + denominator * float(v @ v))) / denominator
    if not tangent > 0:
        raise ValueError(f"no biarc from {a} to {b}")
    join = (a.xy + tangent * ta + b.xy - tangent * tb) / 2.0
    first = arc_to(a, join)
    second = arc_to(first.end, b.xy)
    if abs(wrap_angle(second.end.heading - b.heading)) > 1e-6:
        raise ValueError(f"no biarc from {a} to {b}")
    return [piece for piece in (first, second) if piece.length > 1e-9]
