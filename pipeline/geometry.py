"""Polyline geometry on the hot path of `prepare`: rectangle clipping, arc-length resampling, poses.

Clipping and resampling are numba kernels over many polylines at once (concatenated points plus
offsets): shapely clips one geometry per call and does not promise to keep the driving direction or
say which piece holds the original endpoints, and per-lane numpy calls would dominate the frame time.
shapely is the independent check in the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.kernels import kernel


@dataclass(frozen=True)
class Range:
    """The perception rectangle in the BEV frame (x right, y forward), borders inclusive."""

    x_min: float = -15.0
    x_max: float = 15.0
    y_min: float = -30.0
    y_max: float = 30.0

    @classmethod
    def parse(cls, text: str) -> Range:
        """'30x60' -> x in [-15, 15], y in [-30, 30] (width along x, then length along y)."""
        try:
            width, length = (float(v) for v in text.lower().split("x"))
        except ValueError:
            raise ValueError(f"range {text!r} is not WIDTHxLENGTH in metres, e.g. 30x60") from None
        if width <= 0 or length <= 0:
            raise ValueError(f"range {text!r} must be positive")
        return cls(-width / 2, width / 2, -length / 2, length / 2)

    @property
    def text(self) -> str:
        return f"{self.x_max - self.x_min:g}x{self.y_max - self.y_min:g}"

    @property
    def radius(self) -> float:
        """Distance from the origin to the farthest corner: lanes farther than this are out."""
        return float(np.hypot(max(-self.x_min, self.x_max), max(-self.y_min, self.y_max)))


def ground_height(x, y, ground_z: float, ground_slope) -> np.ndarray:
    """z of the ground under BEV points (x, y): the plane z = ground_z + a x + b y of a frame's
    frames.ground_z and ground_slope (a, b); in the points' float dtype, ground_z itself on level ground."""
    a, b = ground_slope
    return ground_z + a * x + b * y


def pose_matrix(rotation_wxyz, translation) -> np.ndarray:
    """4x4 rigid transform from a (w, x, y, z) quaternion and a translation."""
    from scipy.spatial.transform import Rotation  # 0.2 s to import: loaded where a pose is built

    w, x, y, z = rotation_wxyz
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    T[:3, 3] = translation
    return T


def matrix_quaternion(T: np.ndarray) -> np.ndarray:
    """The (w, x, y, z) quaternion of a 4x4 transform's rotation, with w >= 0."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


# Rotation of the AV2 egovehicle axes (x forward, y left) onto the BEV axes (x right, y forward):
# a point's BEV coordinates are its egovehicle coordinates turned by +90 deg about z.
AV2_EGO_FROM_BEV = np.array([[0.0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


@kernel
def _clip_segment(ax, ay, bx, by, x_min, x_max, y_min, y_max):
    """Liang-Barsky: parameters (t0, t1) of the part of segment a->b inside the box, or (1, 0)."""
    t0, t1 = 0.0, 1.0
    dx, dy = bx - ax, by - ay
    for p, q in ((-dx, ax - x_min), (dx, x_max - ax), (-dy, ay - y_min), (dy, y_max - ay)):
        if p == 0.0:
            if q < 0.0:
                return 1.0, 0.0
        else:
            r = q / p
            if p < 0.0:
                if r > t1:
                    return 1.0, 0.0
                if r > t0:
                    t0 = r
            else:
                if r < t0:
                    return 1.0, 0.0
                if r < t1:
                    t1 = r
    return t0, t1


@kernel
def clip_polylines(xy, offsets, x_min, x_max, y_min, y_max):
    """Clip polylines (points xy[offsets[i]:offsets[i+1]]) to a box, keeping their direction.

    Returns (points, piece_offsets, piece_line, piece_has_start, piece_has_end): the inside parts as
    pieces of >= 2 distinct points; piece_line names the input polyline of each piece; has_start /
    has_end say whether the piece begins at the polyline's first point / ends at its last point.
    """
    n_lines = offsets.shape[0] - 1
    out = np.empty((2 * xy.shape[0] + 2, 2))
    piece_start = np.empty(xy.shape[0] + n_lines + 1, np.int64)
    piece_line = np.empty(xy.shape[0] + n_lines, np.int64)
    has_start = np.zeros(xy.shape[0] + n_lines, np.bool_)
    has_end = np.zeros(xy.shape[0] + n_lines, np.bool_)
    n_out = 0
    n_pieces = 0
    for line in range(n_lines):
        open_piece = False
        started = False  # a piece of this line has begun
        first = offsets[line]
        last = offsets[line + 1] - 1
        for i in range(first, last):
            ax, ay, bx, by = xy[i, 0], xy[i, 1], xy[i + 1, 0], xy[i + 1, 1]
            if ax == bx and ay == by:
                continue
            t0, t1 = _clip_segment(ax, ay, bx, by, x_min, x_max, y_min, y_max)
            if t0 > t1 or (t0 == t1 and not open_piece):
                open_piece = False
                continue
            if not (open_piece and t0 == 0.0):
                piece_start[n_pieces] = n_out
                piece_line[n_pieces] = line
                has_start[n_pieces] = not started and t0 == 0.0 and ax == xy[first, 0] and ay == xy[first, 1]
                has_end[n_pieces] = False
                n_pieces += 1
                # clamped: the interpolated border point can round to just outside the box
                out[n_out, 0] = min(max(ax + t0 * (bx - ax), x_min), x_max)
                out[n_out, 1] = min(max(ay + t0 * (by - ay), y_min), y_max)
                n_out += 1
            ex = bx if t1 == 1.0 else min(max(ax + t1 * (bx - ax), x_min), x_max)
            ey = by if t1 == 1.0 else min(max(ay + t1 * (by - ay), y_min), y_max)
            if ex != out[n_out - 1, 0] or ey != out[n_out - 1, 1]:
                out[n_out, 0] = ex
                out[n_out, 1] = ey
                n_out += 1
            open_piece = t1 == 1.0
        if open_piece:  # the last non-degenerate segment ended inside, at the line's last point
            has_end[n_pieces - 1] = True
    # drop pieces that kept a single point (a line that only touches the box)
    keep = np.ones(n_pieces, np.bool_)
    piece_start[n_pieces] = n_out
    for k in range(n_pieces):
        if piece_start[k + 1] - piece_start[k] < 2:
            keep[k] = False
    n_keep = 0
    n_kept_points = 0
    final_offsets = np.empty(n_pieces + 1, np.int64)
    final_offsets[0] = 0
    points = np.empty((n_out, 2))
    lines = np.empty(n_pieces, np.int64)
    starts = np.empty(n_pieces, np.bool_)
    ends = np.empty(n_pieces, np.bool_)
    for k in range(n_pieces):
        if not keep[k]:
            continue
        m = piece_start[k + 1] - piece_start[k]
        points[n_kept_points : n_kept_points + m] = out[piece_start[k] : piece_start[k + 1]]
        n_kept_points += m
        final_offsets[n_keep + 1] = n_kept_points
        lines[n_keep] = piece_line[k]
        starts[n_keep] = has_start[k]
        ends[n_keep] = has_end[k]
        n_keep += 1
    return (
        points[:n_kept_points],
        final_offsets[: n_keep + 1],
        lines[:n_keep],
        starts[:n_keep],
        ends[:n_keep],
    )


@kernel
def resample_polylines(xy, offsets, n_points):
    """Resample every polyline xy[offsets[i]:offsets[i+1]] to n_points evenly spaced by arc length.

    Endpoints are kept exactly. Returns (n_lines, n_points, 2) and the length of each polyline.
    """
    n_lines = offsets.shape[0] - 1
    out = np.empty((n_lines, n_points, 2))
    lengths = np.zeros(n_lines)
    for line in range(n_lines):
        a, b = offsets[line], offsets[line + 1]
        cum = np.zeros(b - a)
        for i in range(a + 1, b):
            cum[i - a] = cum[i - a - 1] + np.hypot(xy[i, 0] - xy[i - 1, 0], xy[i, 1] - xy[i - 1, 1])
        total = cum[b - a - 1]
        lengths[line] = total
        seg = 0
        for k in range(n_points):
            s = total * k / (n_points - 1) if n_points > 1 else 0.0
            while seg < b - a - 2 and cum[seg + 1] < s:
                seg += 1
            span = cum[seg + 1] - cum[seg] if b - a > 1 else 0.0
            t = (s - cum[seg]) / span if span > 0 else 0.0
            t = min(max(t, 0.0), 1.0)
            j = a + seg
            if b - a == 1:
                out[line, k, 0], out[line, k, 1] = xy[a, 0], xy[a, 1]
            else:
                out[line, k, 0] = xy[j, 0] + t * (xy[j + 1, 0] - xy[j, 0])
                out[line, k, 1] = xy[j, 1] + t * (xy[j + 1, 1] - xy[j, 1])
        if b - a > 1:
            out[line, n_points - 1, 0], out[line, n_points - 1, 1] = xy[b - 1, 0], xy[b - 1, 1]
    return out, lengths
