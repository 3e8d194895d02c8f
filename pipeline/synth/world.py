"""The synthetic worlds: a few hundred metres of road network per world, drawn from the seed, each holding
every hard case of lane-graph targets.

A world (metres; x east, y north; shifted to positive map coordinates at the end):

- a main junction of 4 or 5 arms at irregular angles; every road draws its lane counts per direction
  (1-3) and lane width (3.0-3.8 m); straight connectors lane by lane, left turns from the innermost
  lane, right turns from the outermost, with pedestrian crossings on every arm;
- one arm leads to a one-lane roundabout (ring radius 9.5-12 m, 3-5 arms at irregular angles);
- one arm leads to a T-junction whose cross road meets it at 75-105 degrees;
- one arm carries an exit ramp that forks off its outer lane and merges back (a fork and a merge);
- one arm curves (radius 35-70 m, 50-100 degrees, either way);
- beside the T-junction's arm, a one-way side lane makes an S-bend whose middle segment bulges out of
  the +-15 m lateral range of an ego in the road's outer lane and comes back;
- a fifth arm, when drawn, is a plain straight road; parked cars and street lights along the kerbs.

A draw whose roads overlap (other than where they join) is drawn again from the same generator.
Routes are random walks through the lane graph around a focus (a turn, the ring, the ramp, the bend,
a lane with another of its direction on its right, in either direction), so that the ego drives in
every lane, and not only in the outer one where the ramps and the right turns start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from pipeline.synth.geometry import Pose, turtle
from pipeline.synth.ids import uuid_like
from pipeline.synth.network import Network, Road, Roundabout, WorldLane, arm_distance

# One world per map location: nuScenes has four, AV2 names its cities. Every world drives on the right.
NUSCENES_MAPS = ("boston-seaport", "singapore-onenorth", "singapore-hollandvillage", "singapore-queenstown")
AV2_CITIES = ("PIT", "WDC", "MIA", "ATX")
MAX_WORLDS = len(NUSCENES_MAPS)
MAP_MARGIN_M = 60.0  # empty map around the roads
ENTRY_RADIUS = 6.0
MAX_LANES_PER_WORLD = 1000  # lane ids of world k are (base + k) * 1000 + i
SIDES = ("left", "right")


@dataclass(frozen=True)
class Box:
    """An upright box standing on the ground, in world coordinates: a parked car, a pole."""

    x: float
    y: float
    heading: float
    length: float
    width: float
    height: float


@dataclass(frozen=True)
class Crosswalk:
    """Two edges along the walking direction, as AV2 stores pedestrian crossings: (2, 2) arrays each."""

    edge1: np.ndarray
    edge2: np.ndarray


@dataclass(frozen=True)
class Route:
    """Where one log drives: consecutive lane ids; its frames centre on the route point nearest focus."""

    name: str  # the kind of focus: "junction_left", "roundabout", "fork", "s_bend", "road", ...
    lanes: list[int]
    focus: tuple[float, float]
    speed: float  # m/s


@dataclass(frozen=True)
class Landmarks:
    """The hard cases, in world coordinates, for tests to find."""

    intersection_centre: tuple[float, float]
    intersection_arms: int  # 4 or 5
    intersection_connectors: dict[str, list[int]]  # "left", "straight", "right" -> lane ids
    t_junction_centre: tuple[float, float]
    t_junction_connectors: dict[str, list[int]]
    roundabout_centre: tuple[float, float]
    roundabout_radius: float
    ring_lanes: list[int]  # counter-clockwise; their successors form a cycle
    roundabout_entries: list[int]
    roundabout_exits: list[int]
    roundabout_view: Pose  # ego pose (on the approach) with the whole ring inside the 30 x 60 m crop
    fork_lane: int  # the lane where the exit ramp leaves: two successors
    fork_branches: list[int]  # [road lane, ramp lane]
    merge_lane: int  # the lane where the ramp comes back: two predecessors
    merge_sources: list[int]  # [road lane, ramp lane]
    ramp_lanes: list[int]  # the frontage lane from fork to merge, in driving order
    reentering_lane: int  # one lane segment that leaves the +-15 m lateral range and comes back
    reentering_view: Pose  # ego pose from which reentering_lane does so
    curved_road_lanes: list[int]  # every lane segment of the curved arm's arc


@dataclass
class World:
    seed: int
    index: int  # which world of the seed's dataset
    lanes: dict[int, WorldLane]  # by AV2 lane segment id, ascending
    landmarks: Landmarks
    routes: list[Route]
    parked_cars: list[Box]
    crosswalks: list[Crosswalk]
    poles: list[tuple[float, float]]  # street lights beside the roads (LiDAR clutter)
    buildings: list[Box]  # set back from the kerbs: what the upper LiDAR lasers return from
    canvas: tuple[float, float]  # the map covers [0, w] x [0, h]

    @property
    def nuscenes_map(self) -> str:
        return NUSCENES_MAPS[self.index]

    @property
    def av2_city(self) -> str:
        return AV2_CITIES[self.index]

    def token_of(self, lane_id: int) -> str:
        """The nuScenes token of a lane (a uuid, like the tokens of the real map expansion)."""
        return uuid_like(self.seed, "lane", lane_id)


def build_world(seed: int = 0, index: int = 0) -> World:
    """World `index` of the dataset drawn with `seed`: the same pair always gives the same world."""
    if not 0 <= index < MAX_WORLDS:
        raise ValueError(f"world index must be 0 to {MAX_WORLDS - 1} (one nuScenes map location each)")
    first_id = (int(np.random.default_rng([seed, 0]).integers(20_000, 70_000)) + index) * 1000
    rng = np.random.default_rng([seed, 1, index])
    for _ in range(100):
        state = rng.bit_generator.state
        draft = _draw(rng, first_id, (0.0, 0.0))
        if draft is None:
            continue
        # the same draw again, shifted so that the map starts MAP_MARGIN_M from the roads
        low = np.concatenate(
            [lane.boundary(s).points()[:, :2] for lane in draft.net.lanes.values() for s in SIDES]
        )
        rng.bit_generator.state = state
        parts = _draw(rng, first_id, tuple(MAP_MARGIN_M - low.min(axis=0)))
        assert parts is not None and len(parts.net.lanes) < MAX_LANES_PER_WORLD
        return _world(seed, index, parts, np.random.default_rng([seed, 4, index]))
    raise RuntimeError(f"no non-overlapping layout in 100 draws (seed {seed}, world {index})")


@dataclass
class _Parts:
    net: Network
    landmarks: Landmarks
    route_foci: dict[str, list[tuple[int, tuple[float, float]]]]  # kind -> (focus lane, focus point)
    kerbs: list[tuple[Road, int, str]]  # (road, side, "cars" or "poles"); side -1 is right of the reference
    crossing_roads: list[Road]  # roads with a crossing at their start
    roads: list[Road]  # every road, for the buildings along them


def _draw(rng: np.random.Generator, first_id: int, origin: tuple[float, float]) -> _Parts | None:
    """One layout with the main junction at origin, or None when its roads overlap. The features are
    drawn in this order from `rng`: the same seed gives the same world."""
    net = Network(first_id=first_id)
    arms, junction, count, ramp_shape = _main_junction(net, rng, origin)
    drawn = _roundabout(net, rng, arms["roundabout"])
    if drawn is None:
        return None
    ring, roundabout_arms, view = drawn
    t_centre, cross_roads, t_turns = _t_junction(net, rng, arms["t_junction"])
    fork_lane, merge_lane, ramp = _exit_ramp(net, arms["ramp"], ramp_shape)
    reentering, reentering_view = _s_bend(net, rng, arms["t_junction"])
    curve_arm = arms["curve"]
    curve = sorted(i for lanes_ in curve_arm.forward + curve_arm.backward for i in lanes_
                   if net.lanes[i].path.pieces[0].curvature)  # fmt: skip
    if _overlaps(net):
        return None

    landmarks = Landmarks(
        intersection_centre=origin,
        intersection_arms=count,
        intersection_connectors=junction,
        t_junction_centre=(t_centre.x, t_centre.y),
        t_junction_connectors=t_turns,
        roundabout_centre=ring.centre,
        roundabout_radius=ring.radius,
        ring_lanes=ring.ring,
        roundabout_entries=ring.entries,
        roundabout_exits=ring.exits,
        roundabout_view=view,
        fork_lane=fork_lane,
        fork_branches=list(net.lanes[fork_lane].successors),
        merge_lane=merge_lane,
        merge_sources=list(net.lanes[merge_lane].predecessors),
        ramp_lanes=ramp,
        reentering_lane=reentering,
        reentering_view=reentering_view,
        curved_road_lanes=curve,
    )
    foci = _route_foci(net, landmarks, arms["roundabout"], arms["t_junction"])
    kerbs = [(road, -1, "cars") for road in cross_roads + roundabout_arms[:1]]
    kerbs += [(arms["plain"], -1, "cars")] if "plain" in arms else []
    kerbs += [(road, 1, "poles") for road in [*arms.values(), *cross_roads]]
    kerbs += [(arms["t_junction"], 1, "cars")]
    crossing_roads = [*arms.values(), *cross_roads]
    roads = [*arms.values(), *cross_roads, *roundabout_arms]
    return _Parts(net, landmarks, foci, kerbs, crossing_roads, roads)


def _lane_count(rng: np.random.Generator) -> int:
    return int(rng.integers(1, 4))


def _lane_width(rng: np.random.Generator) -> float:
    return float(rng.uniform(3.0, 3.8))


@dataclass(frozen=True)
class _RampShape:
    """How the exit ramp swings out of its arm's outer lane and back (drawn with the arm, whose middle
    straight spans it)."""

    radius: float
    angle: float  # radians, of each of its four arcs
    straight: float  # metres between its two halves


def _main_junction(
    net: Network, rng: np.random.Generator, origin: tuple[float, float]
) -> tuple[dict[str, Road], dict[str, list[int]], int, _RampShape]:
    """The main junction: 4 or 5 arms at irregular angles, each with its role; returns the arms by role,
    the junction's connectors, the number of arms and the shape of the ramp that the ramp arm carries."""
    ox, oy = origin
    count = int(rng.choice([4, 5]))
    headings = (
        rng.uniform(0, 2 * math.pi)
        + np.arange(count) * 2 * math.pi / count
        + rng.uniform(-1, 1, count) * math.radians(12)
    )
    roles = ["roundabout", "t_junction", "ramp", "curve", "plain"][:count]
    roles = [roles[i] for i in rng.permutation(count)]
    spec = {  # role -> (forward lanes, backward lanes, width): the roundabout takes one lane each way
        role: (1, 1, _lane_width(rng)) if role == "roundabout" else
        (_lane_count(rng), _lane_count(rng), _lane_width(rng)) for role in roles
    }  # fmt: skip
    half = [max(spec[r][0], spec[r][1]) * spec[r][2] for r in roles]
    gaps = np.diff(np.append(headings, headings[0] + 2 * math.pi))
    # far enough out that neighbouring arms' kerbs do not meet: a kerb at half width h clears the
    # neighbour's axis at h / tan(gap / 2)
    distance = max(max(half[i], half[(i + 1) % count]) / math.tan(gaps[i] / 2) + 3.0 for i in range(count))
    arms: dict[str, Road] = {}
    for role, heading in zip(roles, headings, strict=True):
        start = Pose(ox, oy, float(heading)).moved(distance)
        forward, backward, lane_width = spec[role]
        if role == "roundabout":
            steps = [("S", rng.uniform(45, 75))]
        elif role == "t_junction":
            steps = [("S", rng.uniform(90, 120))]
        elif role == "ramp":
            fork_at, rest = rng.uniform(25, 40), rng.uniform(20, 40)
            ramp_angle = math.radians(rng.uniform(20, 30))
            lateral = rng.uniform(lane_width + 1.5, lane_width + 4.0)  # how far out it swings
            ramp_radius = lateral / (2 * (1 - math.cos(ramp_angle)))
            ramp_straight = rng.uniform(6, 20)
            span = 4 * ramp_radius * math.sin(ramp_angle) + ramp_straight
            steps = [("S", fork_at), ("S", span), ("S", rest)]
        elif role == "curve":
            turn = "L" if rng.random() < 0.5 else "R"
            steps = [("S", rng.uniform(10, 20)), (turn, rng.uniform(35, 70), rng.uniform(50, 100)),
                     ("S", rng.uniform(30, 50))]  # fmt: skip
        else:
            steps = [("S", rng.uniform(60, 90))]
        arms[role] = net.road(role, start, steps, forward, backward, lane_width)
    junction = net.junction("intersection", [arms[role].port(True) for role in roles])
    return arms, junction, count, _RampShape(ramp_radius, ramp_angle, ramp_straight)


def _roundabout(
    net: Network, rng: np.random.Generator, street: Road
) -> tuple[Roundabout, list[Road], Pose] | None:
    """The roundabout at the end of the street arm (its axis arrives from the junction) with 3-5 arms of
    its own; returns it, its arms and the view of an ego arriving on the street, or None when its arms
    cannot be at least a ring segment of 5 m apart."""
    ring_radius = float(rng.uniform(9.5, 12.0))
    arm_out = arm_distance(ring_radius, ENTRY_RADIUS, street.width / 2)
    street_end = street.reference[-1].end
    ring_centre = street_end.moved(arm_out)
    # the other arms' outward headings: at least min_gap apart (ring segments of >= 5 m between them)
    theta = math.atan2(street.width / 2 + ENTRY_RADIUS, arm_out)
    min_gap = 2 * theta + 5.0 / ring_radius
    ring_arms = int(rng.integers(3, 6))
    back = street_end.heading + math.pi  # the street's outward heading, seen from the ring
    spread = (2 * math.pi - min_gap * ring_arms) / ring_arms
    if spread < 0:
        return None
    outward = back + np.cumsum(min_gap + rng.uniform(0, 1, ring_arms - 1) * spread)
    roundabout_arms = [
        net.road(
            f"roundabout_arm{k}",
            Pose(ring_centre.x, ring_centre.y, float(h)).moved(arm_out),
            [("S", rng.uniform(30, 45))],
            1,
            1,
            street.width,
        )  # fmt: skip
        for k, h in enumerate(outward)
    ]
    ring = net.roundabout(
        "roundabout", ring_centre, ring_radius, ENTRY_RADIUS,
        [street.port(False)] + [a.port(True) for a in roundabout_arms],
    )  # fmt: skip
    view = Pose(ring_centre.x, ring_centre.y, street_end.heading).moved(
        -(ring_radius + 6.0), -street.width / 2
    )
    return ring, roundabout_arms, view


def _t_junction(
    net: Network, rng: np.random.Generator, stem: Road
) -> tuple[Pose, list[Road], dict[str, list[int]]]:
    """The T-junction at the end of the stem arm, its cross road at 75-105 degrees; returns its centre,
    the cross road's two halves and the junction's connectors."""
    stem_end = stem.reference[-1].end
    cross_lanes, cross_width = int(rng.integers(1, 3)), _lane_width(rng)
    t_distance = max(stem.half_widths) + cross_lanes * cross_width + 3.0
    t_centre = stem_end.moved(t_distance)
    cross = stem_end.heading + math.radians(rng.uniform(75, 105))
    cross_roads = []
    for name, heading in (
        ("t_cross_left", cross),
        ("t_cross_right", cross + math.pi + rng.uniform(-0.15, 0.15)),
    ):
        start = Pose(t_centre.x, t_centre.y, heading).moved(t_distance)
        cross_roads.append(net.road(name, start, [("S", rng.uniform(45, 70))], cross_lanes, cross_lanes,
                                    cross_width))  # fmt: skip
    t_turns = net.junction("t_junction", [stem.port(False)] + [r.port(True) for r in cross_roads])
    return t_centre, cross_roads, t_turns


def _exit_ramp(net: Network, ramp_arm: Road, shape: _RampShape) -> tuple[int, int, list[int]]:
    """The exit ramp from the ramp arm's outer forward lane, back into it after the arm's middle
    straight; returns the fork lane, the merge lane and the ramp's lanes."""
    outer = ramp_arm.forward[-1]
    fork_lane, merge_lane = outer[ramp_arm.step_ends[0]], outer[ramp_arm.step_ends[1] + 1]
    degrees = math.degrees(shape.angle)
    ramp_steps = [("R", shape.radius, degrees), ("L", shape.radius, degrees), ("S", shape.straight),
                  ("L", shape.radius, degrees), ("R", shape.radius, degrees)]  # fmt: skip
    ramp = net.chain("frontage", turtle(net.lanes[fork_lane].path.end, ramp_steps),
                     left_mark="SOLID_WHITE", right_mark="SOLID_WHITE", width=ramp_arm.width)  # fmt: skip
    net.link(fork_lane, ramp[0])
    net.link(ramp[-1], merge_lane)
    return fork_lane, merge_lane, ramp


def _s_bend(net: Network, rng: np.random.Generator, stem: Road) -> tuple[int, Pose]:
    """The S-bend side lane right of the stem arm's outer forward lane: its middle arc starts and ends
    `gap` metres right of that lane's centre and bulges `bulge` metres further out. Returns the lane of
    the middle arc (re-entering the range) and the view of an ego in the outer forward lane, level with
    the bulge's peak."""
    stem_end = stem.reference[-1].end
    bend_deg = float(rng.uniform(30, 40))
    bulge = float(rng.uniform(3.8, 5.5))
    bend_radius = bulge / (1 - math.cos(math.radians(bend_deg)))
    gap = float(rng.uniform(11.8, 12.8))
    ego_offset = -(len(stem.forward) - 0.5) * stem.width  # the outer forward lane, left of the reference
    bend_start = stem.reference[0].start.moved(rng.uniform(20, 35), ego_offset - (gap - bulge))
    bend = turtle(bend_start, [("S", 5), ("R", bend_radius, bend_deg), ("L", bend_radius, 2 * bend_deg),
                               ("R", bend_radius, bend_deg), ("S", 15)])  # fmt: skip
    peak = bend[2].at(bend[2].length / 2)[0]
    if rng.random() < 0.5:  # either driving direction
        bend = [piece.reversed() for piece in reversed(bend)]
    side = net.chain("side_lane", bend, left_mark="SOLID_YELLOW", right_mark="SOLID_WHITE",
                     width=_lane_width(rng))  # fmt: skip
    station = float(
        (peak[:2] - stem.reference[0].start.xy) @ [math.cos(stem_end.heading), math.sin(stem_end.heading)]
    )
    return side[2], stem.reference[0].start.moved(station, ego_offset)


def _route_foci(
    net: Network, landmarks: Landmarks, street: Road, stem: Road
) -> dict[str, list[tuple[int, tuple[float, float]]]]:
    """Where the routes of each kind that ROUTE_KINDS names start from: (focus lane, focus point)."""
    lm = landmarks
    junction, t_turns = lm.intersection_connectors, lm.t_junction_connectors

    def middle(lane: int) -> tuple[int, tuple[float, float]]:
        path = net.lanes[lane].path
        return lane, tuple(float(v) for v in path.at(path.length / 2)[0, :2])

    plain = [i for i, lane in net.lanes.items() if not lane.is_intersection]

    def has_lane_on_right(lane: int) -> bool:
        return net.lanes[lane].right_neighbor is not None

    # "road" and "junction_straight" routes start in a lane with another of its direction on its right
    # where the world has one: the other routes start where ramps and right turns do, in the outer lane.
    inner = [i for i in plain if has_lane_on_right(i)] or plain
    straight_from_inner = [
        i for i in junction["straight"] if any(map(has_lane_on_right, net.lanes[i].predecessors))
    ] or junction["straight"]

    # the outer forward lane segment that the S-bend view stands on
    view, reentering_view = lm.roundabout_view, lm.reentering_view
    view_xy = np.array([reentering_view.x, reentering_view.y])
    ego_lane = min(
        stem.forward[-1], key=lambda i: np.hypot(*(net.lanes[i].centerline()[:, :2] - view_xy).T).min()
    )
    return {  # every kind that ROUTE_KINDS names
        "roundabout": [(street.forward[0][-1], (view.x, view.y))],
        "fork": [(lm.ramp_lanes[0], tuple(float(v) for v in net.lanes[lm.fork_lane].path.end.xy))],
        "s_bend": [(ego_lane, (reentering_view.x, reentering_view.y))],
        "junction_left": [middle(i) for i in junction["left"]],
        "junction_right": [middle(i) for i in junction["right"]],
        "t_junction_turn": [middle(i) for i in t_turns["left"] + t_turns["right"]],
        "merge": [(lm.merge_lane, tuple(float(v) for v in net.lanes[lm.merge_lane].path.start.xy))],
        "curve": [middle(i) for i in lm.curved_road_lanes],
        "road": [middle(i) for i in inner],
        "junction_straight": [middle(i) for i in straight_from_inner],
        "roundabout_through": [middle(i) for i in lm.roundabout_entries],
    }


def _overlaps(net: Network, clearance: float = 0.5) -> bool:
    """Whether lanes of two groups (a road, a junction, the ramp...) that are not linked come within
    `clearance` of each other's lane area: such a layout would put two roads on top of each other."""
    group = {i: lane.name.split("/")[0] for i, lane in net.lanes.items()}
    linked = {frozenset((group[i], group[j])) for i, lane in net.lanes.items() for j in lane.successors}
    names = sorted(set(group.values()))
    areas = {
        name: shapely.union_all([
            shapely.LineString(lane.centerline(1.0)[:, :2]).buffer(
                lane.width / 2 + clearance / 2, cap_style="flat")
            for i, lane in net.lanes.items() if group[i] == name
        ])
        for name in names
    }  # fmt: skip
    for a_index, a in enumerate(names):
        for b in names[a_index + 1 :]:
            if frozenset((a, b)) not in linked and areas[a].intersects(areas[b]):
                return True
    return False


def _world(seed: int, index: int, parts: _Parts, rng: np.random.Generator) -> World:
    net = parts.net
    lanes_area = shapely.union_all(
        [
            shapely.LineString(lane.centerline(1.0)[:, :2]).buffer(lane.width / 2)
            for lane in net.lanes.values()
        ]
    )
    cars = [
        car for road, side, what in parts.kerbs if what == "cars" for car in _parked_cars(rng, road, side)
    ]
    cars = [car for car in cars if not _footprint(car).intersects(lanes_area)]
    poles = [p for road, side, what in parts.kerbs if what == "poles" for p in _poles(road, side)]
    poles = [p for p in poles if lanes_area.distance(shapely.Point(p)) > 0.5]
    crosswalks = [_crosswalk(road) for road in parts.crossing_roads]
    buildings = _buildings(rng, parts.roads, lanes_area)
    xy = np.concatenate([net.lanes[i].boundary(side).points()[:, :2] for i in net.lanes for side in SIDES])
    canvas = tuple(float(math.ceil(v + MAP_MARGIN_M)) for v in xy.max(axis=0))
    assert xy.min() > MAP_MARGIN_M / 2, "the map must stay in positive coordinates"
    routes = _routes(net, parts.route_foci, rng)
    return World(seed, index, dict(sorted(net.lanes.items())), parts.landmarks, routes, cars, crosswalks,
                 poles, buildings, canvas)  # fmt: skip


ROUTE_LENGTH_M = 260.0  # enough for 20 frames 1 s apart at 12 m/s, plus the lead car's gap


# The kinds of route in the order that logs drive them (log i drives route i; validation logs no further
# than routes 8 and 9, pipeline/synth/logs.py): the hard cases first, so that a dataset of a few logs still
# meets them, with routes from inner lanes among them, so that training and validation (a junction from an
# inner lane and the ring) both meet an ego with a lane of its direction on its right.
ROUTE_KINDS = (
    "roundabout",  # the first 8 training logs
    "fork",
    "s_bend",
    "road",
    "junction_left",
    "junction_right",
    "t_junction_turn",
    "junction_straight",
    "junction_straight",  # the 2 validation logs (and training logs 9 and 10 of `cli synth`'s default 16)
    "roundabout_through",
    "merge",  # more training logs
    "curve",
    "road",
)


def _routes(net: Network, foci: dict[str, list], rng: np.random.Generator) -> list[Route]:
    """Two rounds of ROUTE_KINDS: each a random walk through a random focus lane of its kind (backwards
    and forwards, no lane twice)."""
    routes = []
    for kind in ROUTE_KINDS * 2:
        lane, focus = foci[kind][int(rng.integers(len(foci[kind])))]
        routes.append(Route(kind, _walk(net, lane, rng), focus, float(rng.uniform(6.0, 12.0))))
    return routes


def _walk(net: Network, focus: int, rng: np.random.Generator) -> list[int]:
    """Lanes through `focus`: a random walk of about half the route length back, and on forward."""
    lanes, seen = [focus], {focus}
    for forward in (False, True):
        length, lane = 0.0, focus
        while length < ROUTE_LENGTH_M / 2:
            options = [i for i in (net.lanes[lane].successors if forward else net.lanes[lane].predecessors)
                       if i not in seen]  # fmt: skip
            if not options:
                break
            lane = options[int(rng.integers(len(options)))]
            seen.add(lane)
            length += net.lanes[lane].path.length
            if forward:
                lanes.append(lane)
            else:
                lanes.insert(0, lane)
    return lanes


def _footprint(box: Box) -> shapely.Polygon:
    c, s = math.cos(box.heading), math.sin(box.heading)
    corners = [(a * box.length / 2, b * box.width / 2) for a, b in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
    return shapely.Polygon([(box.x + c * u - s * v, box.y + s * u + c * v) for u, v in corners])


def _crosswalk(road: Road) -> Crosswalk:
    """A 3 m wide crossing over a road, 0.5 m past the junction edge where it starts."""
    start = road.reference[0].start
    right, left = road.half_widths
    along = np.array([math.cos(start.heading), math.sin(start.heading)])
    across = np.array([-along[1], along[0]])
    edges = [np.stack([start.xy + d * along - across * (right + 0.5),
                       start.xy + d * along + across * (left + 0.5)]) for d in (0.5, 3.5)]  # fmt: skip
    return Crosswalk(*edges)


def _parked_cars(rng: np.random.Generator, road: Road, side: int) -> list[Box]:
    """Up to three cars at distinct 8 m slots along the road's first piece, beside its outermost lane."""
    cars = []
    reference = road.reference[0]
    slots = int(reference.length // 8) - 1
    if slots < 1:
        return cars
    for s in np.sort(rng.choice(slots, size=min(3, slots), replace=False)) * 8.0 + 6.0:
        spot = Pose(*reference.at(s)[0]).moved(left=side * (road.kerb(side) + 1.2))  # beside the kerb
        heading = spot.heading + (
            math.pi if side > 0 else 0.0
        )  # parked in the driving direction of that side
        length, width, height = rng.uniform(4.3, 4.9), rng.uniform(1.8, 1.95), rng.uniform(1.45, 1.7)
        cars.append(Box(*(float(v) for v in (spot.x, spot.y, heading, length, width, height))))
    return cars


def _buildings(rng: np.random.Generator, roads: list[Road], lanes_area) -> list[Box]:
    """Blocks along both sides of every road, 6-12 m behind the kerb, at least 4 m from any lane and
    apart from each other."""
    buildings: list[Box] = []
    footprints: list[shapely.Polygon] = []
    for road in roads:
        for side in (-1, 1):
            for piece in road.reference:
                for s in np.arange(rng.uniform(0, 10), piece.length, 20.0):
                    length, depth, height = rng.uniform(10, 18), rng.uniform(8, 14), rng.uniform(6, 20)
                    spot = Pose(*piece.at(s)[0]).moved(
                        left=side * (road.kerb(side) + rng.uniform(6, 12) + depth / 2)
                    )
                    box = Box(*(float(v) for v in (spot.x, spot.y, spot.heading, length, depth, height)))
                    footprint = _footprint(box)
                    if lanes_area.distance(footprint) > 4.0 and not any(
                        footprint.intersects(f) for f in footprints
                    ):
                        buildings.append(box)
                        footprints.append(footprint)
    return buildings


def _poles(road: Road, side: int, spacing: float = 30.0) -> list[tuple[float, float]]:
    """Street lights every `spacing` metres, 2.5 m outside the kerb."""
    poles = []
    for piece in road.reference:
        for x, y, heading in piece.at(np.arange(5.0, piece.length, spacing)):
            spot = Pose(x, y, heading).moved(left=side * (road.kerb(side) + 2.5))
            poles.append((float(spot.x), float(spot.y)))
    return poles
