"""The synthetic world: a few hundred metres of road network holding every hard case of lane-graph targets.

Layout (metres, before the seed-dependent shift to positive map coordinates; x east, y north):

- a 4-way intersection at (0, 0): a two-lane-each-way avenue (east-west) crosses a one-lane-each-way
  street (north-south), with left, straight and right connectors and four pedestrian crossings;
- the avenue east of it: an exit ramp forks off its outer eastbound lane at x=50 and, as a frontage
  lane, merges back at x~111 (a fork and a merge);
- the avenue west of it: a 90-degree two-lane-each-way curve (radius 50) to the south;
- the street north of it ends in a roundabout (ring radius 11 m, centre (0, 90)) with four arms;
- the street south of it ends in a T-junction with an east-west road at y=-130;
- beside the street's southern part, a one-way side lane makes an S-bend whose middle segment bulges
  out of the +-15 m lateral range of an ego driving north on the street and comes back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.synth.geometry import Pose, turtle
from pipeline.synth.ids import uuid_like
from pipeline.synth.network import LANE_WIDTH, Network, Road, WorldLane, arm_distance

AV2_CITY = "PIT"  # Pittsburgh and Boston drive on the right, like this world
NUSCENES_MAP = "boston-seaport"
MAP_MARGIN_M = 60.0  # empty map around the roads
RING_RADIUS = 11.0
ENTRY_RADIUS = 6.0
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

    name: str
    lanes: list[int]
    focus: tuple[float, float]
    speed: float  # m/s


@dataclass(frozen=True)
class Landmarks:
    """The hard cases, in world coordinates, for tests to find."""

    intersection_centre: tuple[float, float]
    intersection_connectors: dict[str, list[int]]  # "left", "straight", "right" -> lane ids
    t_junction_centre: tuple[float, float]
    t_junction_connectors: dict[str, list[int]]
    roundabout_centre: tuple[float, float]
    roundabout_radius: float
    ring_lanes: list[int]  # counter-clockwise; their successors form a cycle
    roundabout_entries: list[int]
    roundabout_exits: list[int]
    roundabout_view: Pose  # ego pose (on the approach) with the whole ring inside the 30 x 60 m crop
    fork_lane: int  # the avenue lane where the exit ramp leaves: two successors
    fork_branches: list[int]  # [avenue lane, ramp lane]
    merge_lane: int  # the avenue lane where the ramp comes back: two predecessors
    merge_sources: list[int]  # [avenue lane, ramp lane]
    ramp_lanes: list[int]  # the frontage lane from fork to merge, in driving order
    reentering_lane: int  # one lane segment that leaves the +-15 m lateral range and comes back
    reentering_view: Pose  # ego pose from which reentering_lane does so (the bulge is 1.3 m outside)
    curved_road_lanes: list[int]  # every lane segment of the avenue's 90-degree curve


@dataclass
class World:
    seed: int
    lanes: dict[int, WorldLane]  # by AV2 lane segment id, ascending
    landmarks: Landmarks
    routes: list[Route]
    parked_cars: list[Box]
    crosswalks: list[Crosswalk]
    poles: list[tuple[float, float]]  # street lights beside the roads (LiDAR clutter)
    canvas: tuple[float, float]  # the map covers [0, w] x [0, h]

    def token_of(self, lane_id: int) -> str:
        """The nuScenes token of a lane (a uuid, like the tokens of the real map expansion)."""
        return uuid_like(self.seed, "lane", lane_id)


def build_world(seed: int = 0) -> World:
    rng = np.random.default_rng([seed, 1])
    ox, oy = 140.0 + rng.uniform(0, 20), 195.0 + rng.uniform(0, 20)  # positive nuScenes map coordinates

    def at(x: float, y: float, degrees: float) -> Pose:
        return Pose(ox + x, oy + y, math.radians(degrees))

    net = Network(first_id=int(rng.integers(20_000, 80_000)) * 1000)  # 8-digit ids, like AV2

    # 4-way intersection: roads start at its edges and lead away from it
    av_east = net.road(
        "avenue_east",
        at(9.5, 0, 0),
        [("S", 40.5), ("S", 4 * 30 * math.sin(math.radians(25)) + 10), ("S", 49.3)],
        forward=2,
        backward=2,
    )
    av_west = net.road(
        "avenue_west", at(-9.5, 0, 180), [("S", 10), ("L", 50, 90), ("S", 50)], forward=2, backward=2
    )
    ring_centre = at(0, 90, 0)
    arm = arm_distance(RING_RADIUS, ENTRY_RADIUS, LANE_WIDTH / 2)
    st_north = net.road("street_north", at(0, 13, 90), [("S", 90 - arm - 13)])
    st_south = net.road("street_south", at(0, -13, -90), [("S", 130 - 13 - 9.5)])
    x_turns = net.junction(
        "intersection", [av_east.port(True), st_north.port(True), av_west.port(True), st_south.port(True)]
    )

    # roundabout at the street's north end, three short arms
    arms = [
        net.road(
            f"arm_{name}",
            at(arm * math.cos(math.radians(d)), 90 + arm * math.sin(math.radians(d)), d),
            [("S", 40)],
        )
        for name, d in (("east", 0), ("north", 90), ("west", 180))
    ]
    ring = net.roundabout(
        "roundabout",
        ring_centre,
        RING_RADIUS,
        ENTRY_RADIUS,
        [st_north.port(False)] + [a.port(True) for a in arms],
    )

    # T-junction at the street's south end
    road_e_west = net.road("road_e_west", at(-9.5, -130, 180), [("S", 70.5)])
    road_e_east = net.road("road_e_east", at(9.5, -130, 0), [("S", 70.5)])
    t_turns = net.junction(
        "t_junction", [road_e_east.port(True), st_south.port(False), road_e_west.port(True)]
    )

    # exit ramp from the avenue's outer eastbound lane, back as an on-ramp 61 m later
    outer = av_east.forward[1]
    fork_lane, merge_lane = outer[av_east.step_ends[0]], outer[av_east.step_ends[1] + 1]
    ramp_steps = [("R", 30, 25), ("L", 30, 25), ("S", 10), ("L", 30, 25), ("R", 30, 25)]
    ramp = net.chain(
        "frontage",
        turtle(net.lanes[fork_lane].path.end, ramp_steps),
        left_mark="SOLID_WHITE",
        right_mark="SOLID_WHITE",
    )
    net.link(fork_lane, ramp[0])
    net.link(ramp[-1], merge_lane)

    # S-bend side lane east of the street: its middle arc bulges 16.3 m right of a northbound ego
    bend_r, bend_deg = 24.0, 35.0
    bulge = bend_r * (1 - math.cos(math.radians(bend_deg)))
    side_x = LANE_WIDTH / 2 + 12.0 - bulge  # the middle arc starts and ends 12 m right of the ego lane
    side = net.chain(
        "side_lane",
        turtle(
            at(side_x, -118, 90),
            [
                ("S", 5),
                ("R", bend_r, bend_deg),
                ("L", bend_r, 2 * bend_deg),
                ("R", bend_r, bend_deg),
                ("S", 15),
            ],
        ),
        left_mark="SOLID_YELLOW",
        right_mark="SOLID_WHITE",
    )
    peak_y = -118 + 5 + 2 * bend_r * math.sin(math.radians(bend_deg))

    curve = [
        i
        for lanes in av_west.forward + av_west.backward
        for i in lanes
        if net.lanes[i].path.pieces[0].curvature
    ]
    landmarks = Landmarks(
        intersection_centre=(ox, oy),
        intersection_connectors=x_turns,
        t_junction_centre=(ox, oy - 130),
        t_junction_connectors=t_turns,
        roundabout_centre=ring.centre,
        roundabout_radius=ring.radius,
        ring_lanes=ring.ring,
        roundabout_entries=ring.entries,
        roundabout_exits=ring.exits,
        roundabout_view=at(LANE_WIDTH / 2, 90 - 17.5, 90),
        fork_lane=fork_lane,
        fork_branches=list(net.lanes[fork_lane].successors),
        merge_lane=merge_lane,
        merge_sources=list(net.lanes[merge_lane].predecessors),
        ramp_lanes=ramp,
        reentering_lane=side[2],
        reentering_view=at(LANE_WIDTH / 2, peak_y, 90),
        curved_road_lanes=sorted(curve),
    )

    def middle(lane: int) -> tuple[float, float]:
        path = net.lanes[lane].path
        return tuple(float(v) for v in path.at(path.length / 2)[0, :2])

    def route(name: str, focus: tuple[float, float], speed: float, *waypoints: int) -> Route:
        return Route(name, net.route(*waypoints), focus, speed)

    # the first four are the default logs (3 train, 1 val); together they see every hard case
    north_in, north_out = st_north.forward[0], st_north.backward[0]
    south_in, south_out = st_south.backward[0], st_south.forward[0]
    x_centre, t_centre = landmarks.intersection_centre, landmarks.t_junction_centre
    routes = [
        route("intersection_left_turn", x_centre, 8.0, av_west.backward[0][0], north_in[-1]),
        route("roundabout", _xy(landmarks.roundabout_view), 6.0, north_in[0], arms[2].forward[0][-1]),
        route("fork_and_merge", (ox + 80, oy - 5.25), 12.0, outer[0], outer[-1]),
        route("t_junction_and_s_bend", (ox + LANE_WIDTH / 2, oy - 105), 8.0, road_e_west.backward[0][0],
              south_in[-1]),
        route("frontage_ramp", middle(ramp[2]), 10.0, outer[0], ramp[2], outer[-1]),
        route("curved_avenue", middle(av_west.forward[0][av_west.step_ends[1]]), 10.0, av_east.backward[0][0],
              av_west.forward[0][-1]),
        route("intersection_right_turn", x_centre, 7.0, south_in[0], outer[-1]),
        route("roundabout_from_east", (ox + 17.5, oy + 90 + LANE_WIDTH / 2), 6.0, arms[0].backward[0][0],
              north_out[-1], south_out[-1]),
        route("s_bend", _xy(landmarks.reentering_view), 10.0, south_in[0], south_in[-1]),
        route("t_junction_right_turn", t_centre, 7.0, south_out[0], road_e_west.forward[0][-1]),
    ]  # fmt: skip

    crosswalks = [_crosswalk(road) for road in (av_east, st_north, av_west, st_south)]
    kerbs = [(st_south, -1), (st_south, 1), (st_north, 1), (road_e_west, -1), (road_e_east, -1)]
    cars = _parked_cars(rng, kerbs + [(arms[0], -1)])  # side -1: right of the reference line
    poles = _poles([(av_east, 1), (st_north, -1), (st_south, 1), (road_e_west, 1), (road_e_east, 1)])
    xy = np.concatenate([net.lanes[i].boundary(side).points()[:, :2] for i in net.lanes for side in SIDES])
    canvas = tuple(float(math.ceil(v + MAP_MARGIN_M)) for v in xy.max(axis=0))
    assert xy.min() > MAP_MARGIN_M / 2, "the map must stay in positive coordinates"
    return World(seed, dict(sorted(net.lanes.items())), landmarks, routes, cars, crosswalks, poles, canvas)


def _xy(pose: Pose) -> tuple[float, float]:
    return pose.x, pose.y


def _crosswalk(road: Road) -> Crosswalk:
    """A 3 m wide crossing over a road, 0.5 m past the junction edge where it starts."""
    start = road.reference[0].start
    half_width = LANE_WIDTH * max(len(road.forward), len(road.backward))
    along = np.array([math.cos(start.heading), math.sin(start.heading)])
    across = np.array([-along[1], along[0]]) * (half_width + 0.5)
    edges = [np.stack([start.xy + d * along - across, start.xy + d * along + across]) for d in (0.5, 3.5)]
    return Crosswalk(*edges)


def _parked_cars(rng: np.random.Generator, kerbs: list[tuple[Road, int]]) -> list[Box]:
    """Three cars per kerb, at distinct 8 m slots along the road, beside its outermost lane."""
    cars = []
    for road, side in kerbs:
        reference = road.reference[0]
        lanes = len(road.backward if side > 0 else road.forward)
        slots = np.sort(rng.choice(int(reference.length // 8) - 1, size=3, replace=False)) * 8.0 + 6.0
        for s in slots:
            x, y, heading = reference.at(s)[0]
            left = side * (lanes * LANE_WIDTH + 1.2)  # beside the outermost lane's kerb
            x, y = x - left * math.sin(heading), y + left * math.cos(heading)
            heading += math.pi if side > 0 else 0.0  # parked in the driving direction of that side
            length, width, height = rng.uniform(4.3, 4.9), rng.uniform(1.8, 1.95), rng.uniform(1.45, 1.7)
            cars.append(Box(*(float(v) for v in (x, y, heading, length, width, height))))
    return cars


def _poles(kerbs: list[tuple[Road, int]], spacing: float = 30.0) -> list[tuple[float, float]]:
    """Street lights every `spacing` metres, 2.5 m outside the kerb."""
    poles = []
    for road, side in kerbs:
        reference = road.reference[0]
        lanes = len(road.backward if side > 0 else road.forward)
        for x, y, heading in reference.at(np.arange(5.0, reference.length, spacing)):
            left = side * (lanes * LANE_WIDTH + 2.5)
            poles.append((float(x - left * math.sin(heading)), float(y + left * math.cos(heading))))
    return poles
