"""OpenLane-V2 (subset A: AV2's seven ring cameras; subset B: nuScenes' six): `<root>/<split>/<segment_id>/
info/<timestamp>.json`, one frame per file, read as JSON; the devkit's pickled collections (`*.pkl`) are
never opened (a pickle from elsewhere can run code) and the Map Element Bucket's `<timestamp>-ls.json` not
read. A segment is a log; each frame carries its own lanes (`lane_centerline`, `topology_lclc`), kept as
annotated and turned into the frame's lane graph."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline import io
from pipeline.adapters.av2 import RING_CAMERAS, ground_height
from pipeline.errors import DataError
from pipeline.geometry import AV2_EGO_FROM_BEV
from pipeline.lane_graph import BEV_FROM_OPENLANEV2_EGO, graph_of_annotated
from pipeline.records import AnnotatedLanes, Camera, Frame, Log, LogIndex
from pipeline.targets import FrameTargets, TargetOptions, graph_targets

DATASET = "openlanev2"
SUBSETS = ("A", "B")
NUSCENES_CAMERAS = (
    "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT",
)  # fmt: skip
# (width, height) of each rig's images, for a frame whose image is absent (a present one's header says):
# AV2's front centre camera stands portrait, its other ring cameras and nuScenes' lie landscape
RIG_SIZES = {"ring_front_center": (1550, 2048), **{name: (2048, 1550) for name in RING_CAMERAS[1:]},
             **{name: (1600, 900) for name in NUSCENES_CAMERAS}}  # fmt: skip
GROUND_STEP_M = 0.5  # lanes are sampled this finely for the ground height under the ego
CITY_HEADERS = ({"segment_id", "city"}, {"source_id", "city"}, {"id", "city"})


@dataclass(frozen=True)
class SegmentRef:
    """One segment folder: its split folder, id, frame files in timestamp order and city (--cities; "")."""

    split: str
    segment_id: str
    files: tuple[Path, ...]
    city: str = ""


@dataclass
class FrameFile:
    """What a frame file gives besides its Frame: the annotated lanes, the submission key (split folder,
    segment_id, timestamp as the file names it) and how many of its images are absent."""

    lanes: AnnotatedLanes
    key: tuple[str, str, str]
    images_missing: int


@dataclass
class Segment(Log):
    """A segment read: Log's frames (a file that cannot be read keeps a placeholder, its error in `errors`,
    raised when the frame is prepared, so that --on-error skip passes over that frame alone), and per frame
    id what its file gives."""

    files: dict[str, FrameFile] = field(default_factory=dict)
    errors: dict[str, DataError] = field(default_factory=dict)


def read_cities(path: Path) -> dict[str, str]:
    """--cities: `ID,CITY` per line (a segment_id or the source_id of its meta_data), an optional header
    (`segment_id,city`), blank lines and # comments left out; a bad line is one DataError naming it."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: --cities file not found")
    cities: dict[str, str] = {}
    with open(path, newline="") as stream:
        for number, row in enumerate(csv.reader(stream), 1):
            cells = [cell.strip() for cell in row]
            if not cells or not any(cells) or cells[0].startswith("#"):
                continue
            if number == 1 and set(map(str.lower, cells)) in CITY_HEADERS:
                continue
            if len(cells) != 2 or not all(cells):
                raise DataError(path, f"line {number}", "expected ID,CITY (a segment_id or source_id and "
                                f"its city), got {','.join(row)!r}")  # fmt: skip
            if cities.get(cells[0], cells[1]) != cells[1]:
                raise DataError(path, f"line {number}", f"{cells[0]} is already in city {cities[cells[0]]!r}")
            cities[cells[0]] = cells[1]
    return cities


def frame_files(info: Path) -> tuple[Path, ...]:
    """A segment's `info/<timestamp>.json` files in timestamp order (`-ls.json` files left out)."""
    files = [p for p in info.glob("*.json") if not p.name.endswith("-ls.json")]
    for path in files:
        if not path.stem.isdigit():
            raise DataError(path, "file name", "is not <timestamp>.json (an integer timestamp)")
    return tuple(sorted(files, key=lambda p: int(p.stem)))


def find_segments(
    root: Path, split: str | None, subset: str | None = None, cities: Path | None = None
) -> list[SegmentRef]:
    """Every segment under root/<split>/ with frame files, sorted; with `subset`, those of that subset;
    with `cities` (read_cities), each with its city, a segment the file gives none refused."""
    if not root.is_dir():
        raise DataError(root, "root", "is not a folder (expected the folder that holds train/, val/, ...)")
    city_of = read_cities(cities) if cities else None
    splits = [split] if split else sorted(p.name for p in root.iterdir() if p.is_dir())
    found, seen, of_other_subset = [], {}, 0
    for name in splits:
        folder = root / name
        if not folder.is_dir():
            raise DataError(folder, f"split {name}", "split folder not found")
        for segment in sorted(p for p in folder.iterdir() if (p / "info").is_dir()):
            files = frame_files(segment / "info")
            if not files:
                continue
            if segment.name in seen:
                raise DataError(segment, f"segment {segment.name}", f"is also in {seen[segment.name]}/")
            seen[segment.name] = name
            meta = read_json(files[0]) if subset or city_of is not None else {}
            if subset and subset_of(meta, files[0]) != subset:
                of_other_subset += 1
                continue
            city = segment_city(segment.name, meta, city_of, cities) if city_of is not None else ""
            found.append(SegmentRef(name, segment.name, files, city))
    if not found and of_other_subset:  # else a root without segments, refused as such by the caller
        other, plural = "B" if subset == "A" else "A", "s" * (of_other_subset > 1)
        in_split = f" in split {split}" if split else ""
        holder = "that split" if split else "it"  # the count is of the split looked in
        raise DataError(root, f"--subset {subset}", f"no segment of subset {subset}{in_split} here; {holder} "
                        f"holds subset {other}'s {of_other_subset} segment{plural}")  # fmt: skip
    return found


def subset_of(meta: dict, source: Path) -> str:
    """A or B: by the camera names (AV2's ring cameras or nuScenes'), else by meta_data.source."""
    cameras = set(meta.get("sensor") or {}) if isinstance(meta.get("sensor"), dict) else set()
    if cameras and cameras <= set(RING_CAMERAS):
        return "A"
    if cameras and cameras <= set(NUSCENES_CAMERAS):
        return "B"
    origin = str((meta.get("meta_data") or {}).get("source", "")).lower()
    if "nuscenes" in origin:
        return "B"
    if "av2" in origin or "argoverse" in origin:
        return "A"
    raise DataError(source, "sensor", f"cameras {sorted(cameras)} and meta_data.source {origin!r} are "
                    "neither subset A's (AV2 ring cameras) nor subset B's (nuScenes cameras)")  # fmt: skip


def segment_city(segment_id: str, meta: dict, city_of: dict[str, str], cities: Path) -> str:
    if segment_id in city_of:
        return city_of[segment_id]
    source_id = str((meta.get("meta_data") or {}).get("source_id", ""))
    if source_id in city_of:
        return city_of[source_id]
    raise DataError(cities, f"segment {segment_id}", f"has no city in this file (nor has its source_id "
                    f"{source_id or '(none)'})")  # fmt: skip


def read_json(path: Path) -> dict:
    try:
        value = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:  # a parse error, bad UTF-8, an int of too many digits
        raise DataError(path, "JSON", f"cannot be read: {error}") from error
    except RecursionError:  # Python's reader stops some hundreds of levels deep
        raise DataError(path, "JSON", "cannot be read: arrays or objects nested too deeply") from None
    if not isinstance(value, dict):
        raise DataError(path, "JSON", f"is a {type(value).__name__}, not an object")
    return value


def item(mapping, key: str, source: Path, record: str):
    """mapping[key], or one DataError naming the record and the missing key."""
    if not isinstance(mapping, dict):
        raise DataError(source, record, f"is a {type(mapping).__name__}, not an object")
    if key not in mapping:
        raise DataError(source, record, f"missing key {key!r}")
    return mapping[key]


def numbers(value, shape: tuple[int | None, ...], source: Path, record: str) -> np.ndarray:
    """value as float64 of `shape` (None: any length), all finite, or one DataError naming the record."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as error:
        raise DataError(source, record, "is not an array of numbers") from error
    if array.dtype.kind not in "biuf":  # a float cast would parse strings
        raise DataError(source, record, "is not an array of numbers")
    array = array.astype(np.float64)
    if array.size == 0 and len(shape) == 2 and shape[0] == shape[1] is None:  # [] for a frame without lanes
        array = array.reshape(0, 0)
    if array.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, array.shape)):
        wanted = " x ".join("n" if s is None else str(s) for s in shape)
        raise DataError(source, record, f"has shape {' x '.join(map(str, array.shape))}, not {wanted}")
    if not np.isfinite(array).all():
        raise DataError(source, record, "has non-finite values")
    return array


def rigid(transform, source: Path, record: str) -> np.ndarray:
    """A {rotation 3x3, translation 3} record as a 4x4 matrix."""
    matrix = np.eye(4)
    rotation = item(transform, "rotation", source, record)
    translation = item(transform, "translation", source, record)
    matrix[:3, :3] = numbers(rotation, (3, 3), source, f"{record}.rotation")
    matrix[:3, 3] = numbers(translation, (3,), source, f"{record}.translation")
    return matrix


def read_lanes(annotation, source: Path) -> AnnotatedLanes:
    """lane_centerline and topology_lclc unchanged: points (n >= 2, 3) and links (L, L), ids as strings."""
    centerlines = item(annotation, "lane_centerline", source, "annotation")
    if not isinstance(centerlines, list):
        raise DataError(source, "annotation.lane_centerline", "is not a list")
    points, ids = [], []
    for i, lane in enumerate(centerlines):
        record = f"annotation.lane_centerline[{i}]"
        ids.append(str(item(lane, "id", source, record)))
        points.append(numbers(item(lane, "points", source, record), (None, 3), source, f"{record}.points"))
        if len(points[-1]) < 2:
            problem = f"has {len(points[-1])} point, a lane needs 2 or more"
            raise DataError(source, f"{record}.points", problem)
    links = numbers(item(annotation, "topology_lclc", source, "annotation"), (None, None), source,
                    "annotation.topology_lclc")  # fmt: skip
    if links.shape != (len(points), len(points)):
        raise DataError(source, "annotation.topology_lclc", f"is {links.shape[0]} x {links.shape[1]}, but "
                        f"lane_centerline holds {len(points)} lanes")  # fmt: skip
    return AnnotatedLanes(points, links, ids)


def image_size(root: Path, name: str, image_path: str, source: Path) -> tuple[int, int] | None:
    """(width, height) from the image file's header (PIL reads no pixels); None where the file is absent."""
    path = root / image_path
    if not path.is_file():
        return None
    from PIL import Image

    try:
        with Image.open(path) as image:
            return image.size
    except OSError as error:
        raise DataError(path, f"camera {name} image", f"cannot be read: {error}") from error


def read_cameras(sensor, root: Path, source: Path) -> tuple[list[Camera], int]:
    """The frame's cameras in the BEV frame, and how many of their images are absent."""
    if not isinstance(sensor, dict):
        raise DataError(source, "sensor", "is not an object")
    cameras, missing = [], 0
    for name, camera in sensor.items():
        record = f"sensor.{name}"
        image_path = item(camera, "image_path", source, record)
        if not isinstance(image_path, str):
            raise DataError(source, f"{record}.image_path", "is not a string")
        cam_to_ego = rigid(item(camera, "extrinsic", source, record), source, f"{record}.extrinsic")
        intrinsic = item(camera, "intrinsic", source, record)
        K = item(intrinsic, "K", source, f"{record}.intrinsic")
        K = numbers(K, (3, 3), source, f"{record}.intrinsic.K")
        size = image_size(root, name, image_path, source)
        if size is None:
            missing += 1
            if name not in RIG_SIZES:
                raise DataError(source, record, f"its image {image_path} is absent and camera {name} is of "
                                "no known rig, so its size is unknown")  # fmt: skip
            size = RIG_SIZES[name]
        cameras.append(Camera(name, image_path, K, BEV_FROM_OPENLANEV2_EGO @ cam_to_ego, *map(int, size)))
    return cameras, missing


def check_identity(data: dict, ref: SegmentRef, path: Path) -> None:
    """The file's segment_id and timestamp are those its path names."""
    segment_id, timestamp = item(data, "segment_id", path, "frame"), item(data, "timestamp", path, "frame")
    if str(segment_id) != ref.segment_id:
        problem = f"is {segment_id!r}, but the file lies in segment {ref.segment_id}"
        raise DataError(path, "segment_id", problem)
    if str(timestamp) != path.stem:
        raise DataError(path, "timestamp", f"is {timestamp!r}, but the file is named {path.name}")


def frame_id(ref: SegmentRef, path: Path) -> str:
    return f"{DATASET}/{ref.segment_id}/{path.stem}"


def read_frame(path: Path, ref: SegmentRef, root: Path) -> tuple[Frame, FrameFile]:
    """One frame file: its Frame (pose and cameras in the BEV frame) and FrameFile; DataError if malformed."""
    data = read_json(path)
    check_identity(data, ref, path)
    ego_to_world = rigid(item(data, "pose", path, "frame"), path, "pose")
    cameras, missing = read_cameras(item(data, "sensor", path, "frame"), root, path)
    missing = missing if cameras else 1  # no camera, no image: counted, so that `cli train` refuses it first
    if "annotation" not in data:
        raise DataError(path, "annotation", "missing: a frame without annotations (as in OpenLane-V2's test "
                        "split) gives no lane graph to prepare")  # fmt: skip
    lanes = read_lanes(data["annotation"], path)
    frame = Frame(
        frame_id=frame_id(ref, path), dataset=DATASET, split=ref.split, log_id=ref.segment_id,
        timestamp_ns=int(path.stem),  # as the file names it (subset B: nuScenes' microseconds)
        city=ref.city, ego_to_world=ego_to_world @ AV2_EGO_FROM_BEV, cameras=cameras,
    )  # fmt: skip
    return frame, FrameFile(lanes, (ref.split, ref.segment_id, path.stem), missing)


def load_segment(ref: SegmentRef, root: Path, frame_stride: int = 1) -> Segment:
    """Every `frame_stride`-th frame of the segment, each file read (a malformed one kept as its error);
    ground_z from the annotated lanes near the ego (OpenLane-V2's ego frame shares the BEV frame's origin
    and z), a frame without lanes near it taking the segment's typical height; the ground level."""
    segment = Segment(DATASET, ref.split, ref.segment_id, str(root / ref.split / ref.segment_id), [], [])
    heights = []
    for path in ref.files[::frame_stride]:
        try:
            frame, file = read_frame(path, ref, root)
        except DataError as error:
            frame, file = Frame(frame_id(ref, path), DATASET, ref.split, ref.segment_id, int(path.stem),
                                ref.city, np.eye(4)), None  # fmt: skip
            segment.errors[frame.frame_id] = error
        segment.frames.append(frame)
        if file is not None:
            segment.files[frame.frame_id] = file
            heights.append((frame, ground_height(dense_points(file.lanes), np.eye(4))))
    found = [h for _, h in heights if h is not None]
    typical = float(np.median(found)) if found else 0.0
    for frame, height in heights:
        frame.ground_z = typical if height is None else height
    return segment


def dense_points(lanes: AnnotatedLanes, step_m: float = GROUND_STEP_M) -> np.ndarray:
    """Every lane's points with points added every `step_m` along it: an annotated lane may have none near
    the ego though it passes under it."""
    dense = [np.zeros((0, 3))]
    for points in lanes.points:
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
        at = np.union1d(arc, np.arange(0.0, arc[-1], step_m))
        dense.append(np.stack([np.interp(at, arc, points[:, k]) for k in range(3)], axis=1))
    return np.concatenate(dense)


def index_segment(ref: SegmentRef) -> LogIndex:
    """Every frame's timestamp and world x, y (its pose), and the segment's city, without its lanes."""
    xy = [rigid(item(read_json(path), "pose", path, "frame"), path, "pose")[:2, 3] for path in ref.files]
    timestamps = np.array([int(path.stem) for path in ref.files], np.int64)
    return LogIndex(ref.city, timestamps, np.array(xy, np.float64).reshape(-1, 2))


def frame_targets(segment: Segment, frame: Frame, options: TargetOptions) -> FrameTargets:
    """The frame's targets from its own lanes (graph_of_annotated, cropped to the range); its file's error
    where it could not be read."""
    if frame.frame_id in segment.errors:
        raise segment.errors[frame.frame_id]
    graph = graph_of_annotated(segment.files[frame.frame_id].lanes, options.bev_range)
    return graph_targets(graph, options)


def annotated_table(segment: Segment, frames: list[Frame]) -> pa.Table:
    """The `annotated_lanes` rows of these frames: their lanes and links unchanged, key and missing images."""
    files = [segment.files[frame.frame_id] for frame in frames]
    lanes = [file.lanes for file in files]
    return pa.table(
        {
            "frame_id": pa.array([frame.frame_id for frame in frames], pa.string()),
            "openlanev2_split": pa.array([file.key[0] for file in files], pa.string()),
            "segment_id": pa.array([file.key[1] for file in files], pa.string()),
            "timestamp": pa.array([file.key[2] for file in files], pa.string()),
            "lane_ids": pa.array([lane.ids for lane in lanes], pa.list_(pa.string())),
            "lane_sizes": io.list_array([np.array([len(p) for p in lane.points], np.int32) for lane in lanes],
                                        pa.int32()),
            "points": io.list_array([np.concatenate(lane.points).ravel() if len(lane) else np.zeros(0)
                                     for lane in lanes], pa.float64()),
            "links": io.list_array([np.asarray(lane.links, np.float64).ravel() for lane in lanes],
                                   pa.float64()),
            "images_missing": pa.array([file.images_missing for file in files], pa.int32()),
        }
    )  # fmt: skip
