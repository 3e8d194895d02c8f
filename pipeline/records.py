"""Typed records that travel between the dataset adapters and `prepare`.

Every pose here is expressed for the BEV ego frame of this project: x to the right, y forward,
z up, metres (nuScenes: the LIDAR_TOP sensor frame; AV2: the egovehicle frame turned by +90 deg).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Lane:
    """One lane centerline of a map, in world (city / global) coordinates."""

    id: str
    xyz: np.ndarray  # (n, 3) float64, in driving direction
    successors: list[str]


@dataclass
class Camera:
    name: str
    image_path: str  # relative to the dataset root
    intrinsics: np.ndarray  # (3, 3)
    sensor_to_ego: np.ndarray  # (4, 4), ego = the BEV ego frame
    width: int
    height: int


@dataclass
class Frame:
    frame_id: str  # <dataset>/<log or scene>/<timestamp_ns>
    dataset: str
    split: str
    log_id: str
    timestamp_ns: int
    city: str
    ego_to_world: np.ndarray  # (4, 4) pose of the BEV ego frame in the world frame
    cameras: list[Camera] = field(default_factory=list)
    lidar_path: str = ""  # relative to the dataset root; "" where absent
    lidar_to_ego: np.ndarray = field(default_factory=lambda: np.eye(4))
    ground_z: float = 0.0  # z, in the BEV frame, of the ground under the BEV origin
    # dz/dx, dz/dy of the ground plane in the BEV frame: the ground is z = ground_z + a x + b y (nuScenes:
    # LIDAR_TOP is tilted on the ego; AV2: level)
    ground_slope: list[float] = field(default_factory=lambda: [0.0, 0.0])
    sample_token: str | None = None  # nuScenes: the sample's token, the id other codebases' results use


@dataclass
class AnnotatedLanes:
    """One frame's lane centerlines as OpenLane-V2 annotates them (a frame file's `lane_centerline` and
    `topology_lclc`) or a submission predicts them, unchanged: the input of OpenLane-V2's own DET_l and
    TOP_ll. Points are in OpenLane-V2's ego frame (x forward, y left, z up, metres), not the BEV frame;
    pipeline.lane_graph.graph_of_annotated turns them into a BEV lane graph."""

    points: list[np.ndarray]  # one (n, 3) float64 array per lane, n >= 2, in driving direction
    links: np.ndarray  # (L, L) float64 topology_lclc, lane i -> lane j: 0/1 annotated, probability predicted
    ids: list[str]  # each lane's `id`, as a string
    confidence: np.ndarray | None = None  # (L,) float64, a prediction's lane scores; None: annotated lanes

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class Log:
    """One AV2 log or nuScenes scene: its map lanes and its key frames."""

    dataset: str
    split: str
    log_id: str
    source: str  # the file or folder it was read from, for error messages
    lanes: list[Lane]
    frames: list[Frame]
    map_is_2d: bool = False  # nuScenes maps have no heights: crop with the pose's yaw alone
    pose_source: str = ""  # the file the ego poses came from, for error messages


@dataclass
class LogIndex:
    """Where a log's frames are, read without its map or sensors: what split files of frames and the
    geographic split scheme need before any frame is prepared. Every frame, before --frame-stride."""

    city: str
    timestamps: np.ndarray  # (N,) int64 ns, in frame order
    xy: np.ndarray  # (N, 2) float64 world x, y of each frame's BEV origin (frames.pose_translation)
    sample_tokens: list[str] | None = None  # nuScenes: each frame's sample token
