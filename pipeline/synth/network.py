"""A lane network builder: roads of parallel lanes, junction connectors and roundabouts.

Every lane segment is one `WorldLane` (one AV2 lane segment, one nuScenes lane or lane connector).
Right-hand traffic: a road's forward lanes lie to the right of its reference line.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from pipeline.synth.geometry import Path, Piece, Pose, biarc, fillet, turtle, wrap_angle

LANE_WIDTH = 3.5  # the default; every road draws its own
MAX_SEGMENT_M = 25.0  # reference length of a road's lane segments; lanes outside a curve grow by ~10%
MIN_FILLET_RADIUS_M = 4.0  # tighter corners than this are drawn as a biarc


@dataclass
class WorldLane:
    id: int  # the AV2 lane segment id; the nuScenes token is World.token_of(id)
    name: str  # which road / junction it belongs to, for humans
    path: Path  # centerline in the driving direction
    is_intersection: bool = False  # AV2 is_intersection; a nuScenes lane_connector
    left_mark: str = "NONE"  # AV2 LaneMarkType of the left boundary
    right_mark: str = "NONE"
    width: float = LANE_WIDTH
    successors: list[int] = field(default_factory=list)
    predecessors: list[int] = field(default_factory=list)
    left_neighbor: int | None = None
    right_neighbor: int | None = None

    def centerline(self, spacing: float = 0.25) -> np.ndarray:
        """(n, 3) x, y, z=0 points at most `spacing` apart, through every piece end."""
        xy = self.path.points(spacing)[:, :2]
        return np.column_stack([xy, np.zeros(len(xy))])

    def boundary(self, side: str) -> Path:
        return self.path.offset(self.width / 2 if side == "left" else -self.width / 2)


@dataclass(frozen=True)
class Port:
    """Where a road meets a junction: the lanes entering it and leaving it, innermost first."""

    outward: float  # heading along the road, away from the junction
    incoming: list[int]
    outgoing: list[int]


@dataclass
class Road:
    name: str
    reference: list[Piece]
    forward: list[list[int]]  # [lane, innermost first][segment, in driving order]
    backward: list[list[int]]
    step_ends: list[int]  # index of the forward segment that ends each turtle step
    width: float = LANE_WIDTH  # of every lane

    @property
    def half_widths(self) -> tuple[float, float]:
        """How far the road's kerbs lie right (forward lanes) and left (backward lanes) of its reference."""
        return len(self.forward) * self.width, len(self.backward) * self.width

    def kerb(self, side: int) -> float:
        """How far the kerb on `side` (-1: right, the forward lanes; +1: left) lies from the reference."""
        return self.half_widths[0 if side < 0 else 1]

    def port(self, at_start: bool) -> Port:
        if at_start:
            return Port(
                self.reference[0].start.heading, [b[-1] for b in self.backward], [f[0] for f in self.forward]
            )
        return Port(
            self.reference[-1].end.heading + math.pi,
            [f[-1] for f in self.forward],
            [b[0] for b in self.backward],
        )


@dataclass
class Roundabout:
    centre: tuple[float, float]
    radius: float
    ring: list[int]  # counter-clockwise, a cycle
    entries: list[int]  # one per arm, in the order the arms were given
    exits: list[int]


class Network:
    def __init__(self, first_id: int):
        self.lanes: dict[int, WorldLane] = {}
        self.next_id = first_id

    def add(self, name: str, pieces: list[Piece], **attributes) -> int:
        lane = WorldLane(self.next_id, name, Path(tuple(pieces)), **attributes)
        self.lanes[lane.id] = lane
        self.next_id += 1
        return lane.id

    def link(self, a: int, b: int) -> None:
        """b continues a: the end of a is the start of b."""
        gap = np.hypot(*(self.lanes[a].path.end.xy - self.lanes[b].path.start.xy))
        if gap > 1e-6:
            raise ValueError(
                f"lane {self.lanes[b].name} starts {gap:.3f} m from the end of {self.lanes[a].name}"
            )
        self.lanes[a].successors.append(b)
        self.lanes[b].predecessors.append(a)

    def chain(self, name: str, pieces: list[Piece], **attributes) -> list[int]:
        """One lane segment per piece, each the successor of the one before."""
        ids = [self.add(f"{name}/{i}", [piece], **attributes) for i, piece in enumerate(pieces)]
        for a, b in zip(ids, ids[1:], strict=False):
            self.link(a, b)
        return ids

    def road(
        self,
        name: str,
        start: Pose,
        steps: list[tuple],
        forward: int = 1,
        backward: int = 1,
        width: float = LANE_WIDTH,
    ) -> Road:
        """Parallel lanes along the turtle reference line; every step is cut into segments of at most
        MAX_SEGMENT_M, cut at the same places on every lane so that neighbours line up."""
        reference = turtle(start, steps)
        segments, step_ends = [], []
        for piece in reference:
            segments += piece.split(math.ceil(piece.length / MAX_SEGMENT_M - 1e-9))
            step_ends.append(len(segments) - 1)

        def lanes(count: int, sign: int) -> list[list[int]]:
            out = []
            for i in range(count):
                offset = sign * (i + 0.5) * width
                pieces = [s.offset(offset) for s in segments]
                if sign > 0:  # backward lanes drive against the reference line
                    pieces = [p.reversed() for p in reversed(pieces)]
                centre_mark = "DOUBLE_SOLID_YELLOW" if forward and backward else "SOLID_YELLOW"
                side = "fwd" if sign < 0 else "bwd"
                out.append(
                    self.chain(
                        f"{name}/{side}{i}",
                        pieces,
                        left_mark=centre_mark if i == 0 else "DASHED_WHITE",
                        right_mark="SOLID_WHITE" if i == count - 1 else "DASHED_WHITE",
                        width=width,
                    )
                )
            for inner, outer in zip(out, out[1:], strict=False):
                for a, b in zip(inner, outer, strict=True):
                    self.lanes[a].right_neighbor, self.lanes[b].left_neighbor = b, a
            return out

        return Road(name, reference, lanes(forward, -1), lanes(backward, +1), step_ends, width)

    def connector(self, name: str, a: int, b: int) -> int:
        """A junction lane from the end of a to the start of b: straight-arc-straight where the heading
        lines cross ahead of both ends, else two arcs."""
        start, end = self.lanes[a].path.end, self.lanes[b].path.start
        try:
            pieces = fillet(start, end)
            if any(
                p.curvature and 1.0 / abs(p.curvature) < MIN_FILLET_RADIUS_M or p.length < 0.1 for p in pieces
            ):
                pieces = biarc(start, end)
        except ValueError:
            pieces = biarc(start, end)
        width = (self.lanes[a].width + self.lanes[b].width) / 2
        c = self.add(name, pieces, is_intersection=True, width=width)
        self.link(a, c)
        self.link(c, b)
        return c

    def junction(self, name: str, ports: list[Port]) -> dict[str, list[int]]:
        """Connectors between every pair of arms: straight lane by lane, left turns from the innermost
        lane, right turns from the outermost. Returns the connector ids by kind."""
        turns: dict[str, list[int]] = {"left": [], "straight": [], "right": []}
        for arriving in ports:
            for leaving in ports:
                if leaving is arriving:
                    continue  # no U-turns
                turn = wrap_angle(leaving.outward - (arriving.outward + math.pi))
                if abs(turn) < math.pi / 6:
                    kind = "straight"
                    pairs = [
                        (a, leaving.outgoing[min(i, len(leaving.outgoing) - 1)])
                        for i, a in enumerate(arriving.incoming)
                    ]
                elif turn > 0:
                    kind, pairs = "left", [(arriving.incoming[0], leaving.outgoing[0])]
                else:
                    kind, pairs = "right", [(arriving.incoming[-1], leaving.outgoing[-1])]
                for a, b in pairs:
                    turns[kind].append(self.connector(f"{name}/{kind}", a, b))
        return turns

    def roundabout(
        self, name: str, centre: Pose, radius: float, entry_radius: float, ports: list[Port]
    ) -> Roundabout:
        """A one-lane counter-clockwise ring; each arm's single in and out lane join it with right-turning
        arcs tangent to the ring. The arms' roads must end at `arm_distance` from the centre."""

        def on_ring(angle: float) -> Pose:  # driving counter-clockwise
            return Pose(
                centre.x + radius * math.cos(angle), centre.y + radius * math.sin(angle), angle + math.pi / 2
            )

        entries, exits, points = [], [], []  # points: (ring angle, "entry" or "exit", lane)
        for arm, port in enumerate(ports):
            (incoming,), (outgoing,) = port.incoming, port.outgoing
            offset = self._lateral(incoming, centre.xy, port.outward)
            theta = math.atan2(offset + entry_radius, arm_distance(radius, entry_radius, offset))
            sweep = math.pi / 2 - theta  # the entry arc turns right from the arm heading to the ring tangent
            entry_arc = Piece(self.lanes[incoming].path.end, -1.0 / entry_radius, entry_radius * sweep)
            exit_angle = port.outward - theta  # the mirror image of the entry, driven the other way
            exit_arc = Piece(on_ring(exit_angle), -1.0 / entry_radius, entry_radius * sweep)
            entries.append(self.add(f"{name}/entry{arm}", [entry_arc], is_intersection=True))
            exits.append(self.add(f"{name}/exit{arm}", [exit_arc], is_intersection=True))
            self.link(incoming, entries[-1])
            self.link(exits[-1], outgoing)
            points += [
                ((port.outward + theta) % (2 * math.pi), "entry", entries[-1]),
                (exit_angle % (2 * math.pi), "exit", exits[-1]),
            ]
        points.sort()
        ring = []
        for i, (angle, _, _) in enumerate(points):
            sweep = (points[(i + 1) % len(points)][0] - angle) % (2 * math.pi)
            piece = Piece(on_ring(angle), 1.0 / radius, radius * sweep)
            ring.append(
                self.add(f"{name}/ring{i}", [piece], left_mark="SOLID_YELLOW", right_mark="SOLID_WHITE")
            )
        for i, (_, kind, lane) in enumerate(points):
            before, after = ring[i - 1], ring[i]  # the ring segments that end and start at this point
            self.link(before, after)
            if kind == "exit":
                self.link(before, lane)
            else:
                self.link(lane, after)
        return Roundabout((centre.x, centre.y), radius, ring, entries, exits)

    def _lateral(self, lane: int, centre: np.ndarray, outward: float) -> float:
        """How far left of the arm's outward axis the lane ends (the in lane of a right-hand road: > 0)."""
        d = self.lanes[lane].path.end.xy - centre
        return float(-d[0] * math.sin(outward) + d[1] * math.cos(outward))

    def route(self, *waypoints: int) -> list[int]:
        """Lane ids from the first waypoint through the others, fewest segments between each pair."""
        lanes = [waypoints[0]]
        for a, b in zip(waypoints, waypoints[1:], strict=False):
            lanes += self._shortest(a, b)[1:]
        return lanes

    def _shortest(self, a: int, b: int) -> list[int]:
        came_from, queue = {a: a}, deque([a])
        while queue:
            lane = queue.popleft()
            if lane == b:
                path = [b]
                while path[-1] != a:
                    path.append(came_from[path[-1]])
                return path[::-1]
            for nxt in self.lanes[lane].successors:
                if nxt not in came_from:
                    came_from[nxt] = lane
                    queue.append(nxt)
        raise ValueError(f"no route from {self.lanes[a].name} to {self.lanes[b].name}")


def arm_distance(radius: float, entry_radius: float, offset: float) -> float:
    """Distance from a roundabout's centre, along an arm, at which the in lane (offset metres left of the
    arm axis) starts its entry arc: that arc's circle touches the ring from outside."""
    return math.sqrt((radius + entry_radius) ** 2 - (offset + entry_radius) ** 2)
