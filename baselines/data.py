"""Training samples from a prepared dataset (docs/guide/prepare.md) and the raw sensor files it points to.

Real nuScenes / AV2 and the synthetic data go through the same code: images (cv2) resized by the
paper's ratio (0.5 nuScenes, 0.3 AV2), LiDAR sweeps (nuScenes `.pcd.bin` float32 x 5, AV2 `.feather`)
moved into the BEV frame. Targets: the paths' points resampled to N, in unit BEV coordinates, and a
lane mask on the BEV grid for the auxiliary segmentation.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, fields, replace
from pathlib import Path

import cv2
import numpy as np
import pyarrow.compute as pc
import pyarrow.feather as feather
import torch

from baselines.config import Config, Rig
from baselines.layers.bev_encoder import SensorBatch
from baselines.layers.targets import Targets
from pipeline.adapters.av2 import RING_CAMERAS
from pipeline.camera import scaled_intrinsics
from pipeline.geometry import ground_height
from pipeline.io import decode_raster, read_table
from pipeline.manifest import PreparedData, is_synthetic


@dataclass
class Sample:
    frame_id: str
    images: np.ndarray | None  # (Ncam, 3, H, W) uint8 RGB, zero-padded (the model normalises)
    intrinsics: np.ndarray | None  # (Ncam, 3, 3)
    sensor_to_ego: np.ndarray | None  # (Ncam, 4, 4)
    image_sizes: np.ndarray | None  # (Ncam, 2) height, width before padding
    points: np.ndarray | None  # (P, 4) x, y, z, intensity (0..1) in the BEV frame
    paths: np.ndarray  # (G, N, 2) unit BEV coordinates
    seg: np.ndarray  # (bev_h, bev_w) int64: 1 lane, 0 background
    ground_z: float  # z of the ground under the BEV origin, in the BEV frame (frames.ground_z)
    ground_slope: tuple[float, float]  # dz/dx, dz/dy of the ground plane, BEV frame (frames.ground_slope)
    raster: tuple[np.ndarray, np.ndarray] | None = None  # prepared (mask, direction bins), when needed
    pieces: np.ndarray | None = None  # (P, n, 2) unit BEV coordinates, when needed
    piece_links: np.ndarray | None = None  # (L, 2) int64 (src piece, dst piece), when needed


def resample_polyline(xy: np.ndarray, n: int) -> np.ndarray:
    """(m, 2) polyline -> (n, 2) points evenly spaced by arc length, ends kept."""
    if len(xy) == 1:
        return np.repeat(xy, n, 0)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    if arc[-1] <= 0:
        return np.repeat(xy[:1], n, 0)
    t = np.linspace(0.0, arc[-1], n)
    return np.stack([np.interp(t, arc, xy[:, 0]), np.interp(t, arc, xy[:, 1])], 1)


def decoded_extent(decoded: int, size: int, reduction: int) -> int:
    """How many pixels of the full-size image (`size` of them) the `decoded` pixels of an image read at
    1/reduction span. A JPEG decoded at 1/r gives ceil(size / r) pixels of r x r full-size pixels each, the
    last one partly the encoder's edge padding: decoded * r (904 rows for 900 at 1/8), not size. OpenCV
    resizes other formats to floor(size / r) pixels over the whole image: size."""
    return decoded * reduction if decoded * reduction >= size else size


def read_image(path: Path, scale: float, width: int, height: int) -> tuple[np.ndarray, float, float]:
    """RGB uint8 image (H, W, 3) of the camera of calibrated size `width` x `height`, resized by `scale`;
    returns it with the exact x / y scale factors: full-size pixel u is at (u + 0.5) * s - 0.5 in it."""
    # JPEG decodes at 1/2, 1/4 or 1/8 size directly, several times faster than a full decode: use
    # the smallest one still at least as large as the target.
    reduction = max(r for r in (1, 2, 4, 8) if 1 / r >= scale)
    flags = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
             8: cv2.IMREAD_REDUCED_COLOR_8}  # fmt: skip
    image = cv2.imread(str(path), flags[reduction])
    if image is None:
        raise FileNotFoundError(f"{path}: image missing or unreadable")
    if reduction == 1:
        height, width = image.shape[:2]
    new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
    # the scale of the decoded image's own extent: a 900-row JPEG at 1/8 decodes to 113 rows of 8, whose
    # 904 rows the resize to 112 maps (the scale 112 / 900 would put the bottom rows 0.5 px off)
    extent_w = decoded_extent(image.shape[1], width, reduction)
    extent_h = decoded_extent(image.shape[0], height, reduction)
    if (new_w, new_h) != (image.shape[1], image.shape[0]):
        image = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB), new_w / extent_w, new_h / extent_h


def camera_rig(frame: dict) -> Rig:
    """Whose image settings (config.DataConfig) a prepared frame's cameras take: its dataset's on nuScenes
    and AV2; an OpenLane-V2 frame's by its cameras, AV2's for subset A's seven ring cameras and nuScenes'
    for subset B's six CAM_ ones (one root may hold both). Other cameras are a ValueError naming them."""
    if frame["dataset"] in ("nuscenes", "av2"):
        return frame["dataset"]
    names = sorted(camera["name"] for camera in frame["cameras"])
    if names and all(name in RING_CAMERAS for name in names):
        return "av2"
    if names and all(name.startswith("CAM_") for name in names):
        return "nuscenes"
    raise ValueError(f"{frame['frame_id']}: cameras {', '.join(names) or 'none'} are neither AV2's ring "
                     "cameras (OpenLane-V2 subset A) nor nuScenes' CAM_ cameras (subset B): no image "
                     "settings for them")  # fmt: skip


def height_above_ground(points: np.ndarray, ground_z: float, ground_slope) -> np.ndarray:
    """(P,) height of float32 BEV points (P, >= 3) above the ground plane z = ground_z + a x + b y
    (frames.ground_z, ground_slope), in float32: on level ground, the points' z minus ground_z bit for bit."""
    return points[:, 2] - ground_height(points[:, 0], points[:, 1], ground_z, ground_slope)


def read_lidar(path: Path) -> np.ndarray:
    """(P, 4) x, y, z, intensity 0..1 in the sensor's frame (AV2: the egovehicle frame)."""
    if path.name.endswith(".bin"):  # nuScenes .pcd.bin: x, y, z, intensity, ring index
        points = np.fromfile(path, np.float32).reshape(-1, 5)[:, :4].copy()
    elif path.suffix == ".feather":
        table = feather.read_table(path, columns=["x", "y", "z", "intensity"])
        points = np.stack([table[c].to_numpy().astype(np.float32) for c in ("x", "y", "z", "intensity")], 1)
    else:
        raise ValueError(f"{path}: unknown LiDAR format (expected .pcd.bin or .feather)")
    points[:, 3] /= 255.0  # both datasets store intensity as 0..255
    return points


def lane_mask_from_raster(mask: np.ndarray, bev_h: int, bev_w: int) -> np.ndarray:
    """A decoded `rasters` lane mask on the BEV grid: a BEV cell is lane if any raster cell inside it is."""
    if mask.shape[0] % bev_h == 0 and mask.shape[1] % bev_w == 0:
        fy, fx = mask.shape[0] // bev_h, mask.shape[1] // bev_w
        return mask.reshape(bev_h, fy, bev_w, fx).max(axis=(1, 3)).astype(np.int64)
    resized = cv2.resize(mask.astype(np.float32), (bev_w, bev_h), interpolation=cv2.INTER_AREA)
    return (resized > 0).astype(np.int64)


def lane_mask_from_paths(paths_unit: np.ndarray, bev_h: int, bev_w: int) -> np.ndarray:
    """Lane mask drawn from the paths' polylines, for datasets prepared without rasters."""
    mask = np.zeros((bev_h, bev_w), np.uint8)
    scale = np.array([bev_w, bev_h], np.float64)
    for path in paths_unit:
        pixels = np.round(path * scale * 16 - 0.5 * 16).astype(np.int32)  # 4 fractional bits
        cv2.polylines(mask, [pixels], False, 1, 1, cv2.LINE_8, shift=4)
    return mask.astype(np.int64)


class PreparedDataset(torch.utils.data.Dataset):
    """The frames of one split of a prepared dataset, with their sensors and the targets that a model
    `needs` ("paths", "raster"; see baselines/models); the lane mask on the BEV grid always."""

    def __init__(
        self, data: PreparedData, split: str, config: Config, needs: frozenset[str] = frozenset({"paths"})
    ):
        self.data_dir = data.path
        self.config = config
        manifest_path = self.data_dir / "manifest.json"
        self.sensor_root = Path(config.data.sensor_root) if config.data.sensor_root else data.sensor_root
        self.synthetic = is_synthetic(self.sensor_root)
        crop = data.crop
        model_range = (tuple(config.encoder.x_range), tuple(config.encoder.y_range))
        if crop is not None and crop != model_range:
            # targets outside the model's grid would be wrong without a word (unit coordinates beyond [0, 1])
            raise ValueError(
                f"{manifest_path}: the dataset is cropped to x {crop[0]}, y {crop[1]} m but the model's BEV "
                f"grid covers x {model_range[0]}, y {model_range[1]} m; train on it (cli train takes the "
                "dataset's range) or re-prepare with that --range"
            )
        in_split = pc.field("split") == split
        frames = read_table(self.data_dir, "frames", filter=in_split).sort_by("frame_id").to_pylist()
        if not frames:
            splits = sorted(data.split_sizes)
            raise ValueError(
                f"{self.data_dir}: no frames in split {split!r}; its splits are {', '.join(splits)} "
                "(choose with --set train.train_split=... / train.val_split=..., or `cli eval --split`)"
            )
        unknown = [f["frame_id"] for f in frames if f["ground_z"] is None]
        if unknown:
            raise ValueError(f"{self.data_dir / 'frames'}: frame {unknown[0]}: ground_z is null")
        unknown = [f["frame_id"] for f in frames if f["ground_slope"] is None or len(f["ground_slope"]) != 2]
        if unknown:
            raise ValueError(f"{self.data_dir / 'frames'}: frame {unknown[0]}: ground_slope is not 2 numbers")
        self.frames = frames
        self.needs = needs
        frame_ids = set(f["frame_id"] for f in frames)
        in_frames = pc.field("frame_id").isin(sorted(frame_ids))
        self.path_points = getattr(config.decoder, "path_points", 0)
        self.paths = {frame_id: [] for frame_id in frame_ids}
        if "paths" in needs:
            self.paths |= self._polylines("paths", "path_index", self.path_points, in_frames)
        self.piece_points = getattr(config.decoder, "piece_points", 0)
        self.pieces = {frame_id: [] for frame_id in frame_ids}
        self.piece_links: dict[str, list[tuple[int, int]]] = {frame_id: [] for frame_id in frame_ids}
        if "pieces" in needs:
            self.pieces |= self._polylines("pieces", "piece_index", self.piece_points, in_frames)
            links = read_table(self.data_dir, "piece_links", filter=in_frames).to_pylist()
            for row in links:
                self.piece_links[row["frame_id"]].append((row["src_piece"], row["dst_piece"]))
        self.cache: dict[int, Sample] = {}  # filled when config.data.cache_samples
        self.rasters: dict[str, dict] = {}
        if (self.data_dir / "rasters").is_dir():
            for row in read_table(self.data_dir, "rasters", filter=in_frames).to_pylist():
                self.rasters[row["frame_id"]] = row
        elif "raster" in needs:
            raise ValueError(f"{self.data_dir}: no rasters table (prepare the dataset with its rasters)")

    def _polylines(self, table: str, index: str, n: int, in_frames) -> dict[str, list[np.ndarray]]:
        """{frame_id: [(n, 2) unit BEV coordinates, ...] in index order} of the paths or pieces table:
        the prepared resampled points when they are n, else the full polyline resampled to n."""
        columns = ["frame_id", index, "x", "y", "rx", "ry"]
        rows = read_table(self.data_dir, table, columns=columns, filter=in_frames)
        out: dict[str, list[np.ndarray]] = {}
        for row in rows.sort_by([("frame_id", "ascending"), (index, "ascending")]).to_pylist():
            polylines = out.setdefault(row["frame_id"], [])
            if len(polylines) != row[index]:
                where = f"{self.data_dir / table}: frame {row['frame_id']}"
                raise ValueError(f"{where}: {index} is not 0, 1, 2, ...")
            if len(row["rx"]) == n:
                xy = np.stack([row["rx"], row["ry"]], 1)
            else:
                xy = resample_polyline(np.stack([row["x"], row["y"]], 1).astype(np.float64), n)
            polylines.append(self.config.encoder.metres_to_unit(xy.astype(np.float32)))
        return out

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> Sample:
        if index in self.cache:
            return self.cache[index]
        frame = self.frames[index]
        config = self.config
        modality = config.encoder.modality
        paths = self.paths[frame["frame_id"]]
        n = self.path_points
        paths_unit = np.stack(paths).astype(np.float32) if paths else np.zeros((0, n, 2), np.float32)
        bev_h, bev_w = config.encoder.bev_h, config.encoder.bev_w
        raster = self.rasters.get(frame["frame_id"])
        decoded = decode_raster(raster) if raster is not None else None  # once: seg and "raster" use it
        if decoded is not None:
            seg = lane_mask_from_raster(decoded[0], bev_h, bev_w)
        else:
            seg = lane_mask_from_paths(paths_unit, bev_h, bev_w)
        sample = Sample(frame["frame_id"], None, None, None, None, None, paths_unit, seg, frame["ground_z"],
                        tuple(frame["ground_slope"]))  # fmt: skip
        if "raster" in self.needs:
            sample.raster = decoded
        if "pieces" in self.needs:
            pieces = self.pieces[frame["frame_id"]]
            shape = (0, self.piece_points, 2)
            sample.pieces = np.stack(pieces).astype(np.float32) if pieces else np.zeros(shape, np.float32)
            sample.piece_links = np.array(self.piece_links[frame["frame_id"]], np.int64).reshape(-1, 2)
        if modality in ("camera", "fusion"):
            self._load_cameras(frame, sample)
        if modality in ("lidar", "fusion"):
            sample.points = self._load_lidar(frame, index)
        if self.config.data.cache_samples:
            self.cache[index] = sample
        return sample

    def _load_cameras(self, frame: dict, sample: Sample) -> None:
        cameras = frame["cameras"]
        if not cameras:
            raise ValueError(f"{frame['frame_id']}: no cameras in the prepared frame (camera modality)")
        data = self.config.data
        scale, crop_top = data.image_settings(camera_rig(frame), self.synthetic)
        images, intrinsics, extrinsics, sizes = [], [], [], []
        for camera in cameras:
            path = self.sensor_root / camera["image_path"]
            image, scale_x, scale_y = read_image(path, scale, camera["width"], camera["height"])
            top = int(crop_top * image.shape[0])
            image = image[top:]
            k = scaled_intrinsics(np.array(camera["intrinsics"], np.float64).reshape(3, 3), scale_x, scale_y)
            k[1, 2] -= top  # the rows cut off the top move the principal point up
            images.append(image)
            intrinsics.append(k)
            extrinsics.append(np.array(camera["sensor_to_ego"], np.float64).reshape(4, 4))
            sizes.append(image.shape[:2])
        divisor = data.image_divisor
        height = -(-max(s[0] for s in sizes) // divisor) * divisor
        width = -(-max(s[1] for s in sizes) // divisor) * divisor
        # AV2's front camera is portrait, the others landscape: pad all to one size (bottom / right,
        # which leaves the pixel coordinates and so the intrinsics unchanged). uint8 until the model:
        # a quarter of the bytes to convert, copy to the main process and move to the GPU.
        padded = np.zeros((len(images), 3, height, width), np.uint8)
        for i, image in enumerate(images):
            padded[i, :, : image.shape[0], : image.shape[1]] = image.transpose(2, 0, 1)
        sample.images = padded
        sample.intrinsics = np.stack(intrinsics).astype(np.float32)
        sample.sensor_to_ego = np.stack(extrinsics).astype(np.float32)
        sample.image_sizes = np.array(sizes, np.int64)

    def _load_lidar(self, frame: dict, index: int) -> np.ndarray:
        if not frame["lidar_path"]:
            raise ValueError(f"{frame['frame_id']}: no LiDAR sweep in the prepared frame (lidar modality)")
        points = read_lidar(self.sensor_root / frame["lidar_path"])
        lidar_to_ego = np.array(frame["lidar_to_ego"], np.float64).reshape(4, 4)
        points[:, :3] = (
            points[:, :3].astype(np.float64) @ lidar_to_ego[:3, :3].T + lidar_to_ego[:3, 3]
        ).astype(np.float32)
        encoder = self.config.encoder
        (x0, x1), (y0, y1), (z0, z1) = encoder.x_range, encoder.y_range, encoder.z_range
        x, y = points[:, 0], points[:, 1]
        z = height_above_ground(points, frame["ground_z"], frame["ground_slope"])  # z_range: above the ground
        points = points[(x >= x0) & (x <= x1) & (y >= y0) & (y <= y1) & (z >= z0) & (z <= z1)]
        limit = self.config.data.max_points
        if len(points) > limit:
            # A fixed subset per frame, so that an epoch is reproducible whatever the worker.
            rng = np.random.default_rng(zlib.crc32(frame["frame_id"].encode()))
            points = points[np.sort(rng.choice(len(points), limit, replace=False))]
        return points


@dataclass
class Batch:
    frame_ids: list[str]
    sensors: SensorBatch
    targets: Targets

    def to(self, device: torch.device | str) -> Batch:
        return Batch(self.frame_ids, self.sensors.to(device), self.targets.to(device))

    def pin_memory(self) -> Batch:
        """The batch in page-locked memory (the DataLoader's pin_memory calls it), so that `to(device)`
        copies asynchronously."""
        return Batch(self.frame_ids, pinned(self.sensors), pinned(self.targets))


def pinned(record):
    """A dataclass of tensors, lists of tensors and None with every tensor in page-locked memory."""

    def pin(value):
        if isinstance(value, list):
            return [v.pin_memory() for v in value]
        return None if value is None else value.pin_memory()

    return replace(record, **{f.name: pin(getattr(record, f.name)) for f in fields(record)})


def collate(samples: list[Sample]) -> Batch:
    sensors = SensorBatch(
        ground_z=torch.tensor([s.ground_z for s in samples], dtype=torch.float32),
        ground_slope=torch.tensor([s.ground_slope for s in samples], dtype=torch.float32).view(-1, 2),
    )
    if samples[0].images is not None:
        height = max(s.images.shape[2] for s in samples)
        width = max(s.images.shape[3] for s in samples)
        images = np.zeros((len(samples), samples[0].images.shape[0], 3, height, width), np.uint8)
        for i, s in enumerate(samples):
            images[i, :, :, : s.images.shape[2], : s.images.shape[3]] = s.images
        sensors.images = torch.from_numpy(images)
        sensors.intrinsics = torch.from_numpy(np.stack([s.intrinsics for s in samples]))
        sensors.sensor_to_ego = torch.from_numpy(np.stack([s.sensor_to_ego for s in samples]))
        sensors.image_sizes = torch.from_numpy(np.stack([s.image_sizes for s in samples]))
    if samples[0].points is not None:
        count = max(1, max(len(s.points) for s in samples))
        points = np.zeros((len(samples), count, 4), np.float32)
        mask = np.zeros((len(samples), count), bool)
        for i, s in enumerate(samples):
            points[i, : len(s.points)] = s.points
            mask[i, : len(s.points)] = True
        sensors.points, sensors.points_mask = torch.from_numpy(points), torch.from_numpy(mask)
    targets = Targets(
        [torch.from_numpy(s.paths) for s in samples], torch.from_numpy(np.stack([s.seg for s in samples]))
    )
    if samples[0].raster is not None:
        targets.raster_mask = torch.from_numpy(np.stack([s.raster[0] for s in samples]))
        targets.raster_direction = torch.from_numpy(np.stack([s.raster[1] for s in samples]))
    if samples[0].pieces is not None:
        targets.pieces = [torch.from_numpy(s.pieces) for s in samples]
        targets.piece_links = [torch.from_numpy(s.piece_links) for s in samples]
    return Batch([s.frame_id for s in samples], sensors, targets)
