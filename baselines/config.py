"""Configuration as plain dataclasses: the shared encoder, the data and the training, with the `paper`,
`tiny` and `gpu` presets of them. A model's head config (the `decoder` section) and its size per preset
live beside the model (baselines/models/); `baselines.models.resolve_config` puts a preset and a model
together, `baselines.models.load_config` reads a saved one.

Every field can be overridden from the command line with `--set section.field=value`
(e.g. `--set train.lr=3e-4 --set encoder.kernel_size=3,3`); the resolved config is saved with the run.
A numeric field's valid values stand beside it (`Annotated[int, AT_LEAST_1]`, a `Range`); a value outside
them is an error naming the field, whichever way it came: a preset, an option, `--set` or a saved config;
so are fields that the model's build needs together (attention heads dividing the channels), once all are set.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch

Modality = Literal["camera", "lidar", "fusion"]
Rig = Literal["nuscenes", "av2"]  # whose cameras: their image settings (DataConfig.image_settings)
BackboneName = Literal["resnet18", "resnet34", "resnet50"]
# A validation's scores (RUN/val.jsonl, baselines/validate.py) that choose best.pt (train.best_metric).
BestMetric = Literal[
    "directed_topo_f1",
    "directed_junction_topo_f1",
    "undirected_topo_f1",
    "undirected_junction_topo_f1",
    "miou",
]


@dataclass(frozen=True)
class Range:
    """The values a numeric config field may take (each element's, in a tuple field): low <= value <= high,
    `<` at an open end; `increasing`: a tuple's elements strictly increase. A value must be finite (NaN
    and +-infinity are refused) unless `infinite` allows an infinite end (train.grad_clip: inf, no
    clipping)."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = True
    increasing: bool = False
    infinite: bool = False

    def holds(self, value: float) -> bool:
        if not math.isfinite(value) and not (self.infinite and not math.isnan(value)):
            return False
        above = self.low < value if self.low_open else self.low <= value
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def describe(self) -> str:
        """E.g. `at least 1`, `greater than 0`, `in [0, 1)`."""
        if self.high == math.inf and self.high_open:
            if self.low == -math.inf:
                return "finite"
            return f"greater than {self.low}" if self.low_open else f"at least {self.low}"
        return f"in {'(' if self.low_open else '['}{self.low}, {self.high}{')' if self.high_open else ']'}"

    def problem(self, value: Any) -> str | None:
        """What is wrong with `value` (`must be at least 0, not -1`), or None when it is in range."""
        if isinstance(value, tuple):
            if not all(self.holds(item) for item in value):
                return f"must be {self.describe()} each, not {value}"
            if self.increasing and any(a >= b for a, b in zip(value, value[1:])):
                return f"must be increasing, not {value}"
            return None
        return None if self.holds(value) else f"must be {self.describe()}, not {value}"


# The ranges most fields share.
AT_LEAST_0 = Range(low=0)  # counts where 0 means none, off or automatic; loss weights (0: a term off)
AT_LEAST_1 = Range(low=1)  # counts and sizes
POSITIVE = Range(low=0, low_open=True)  # rates, scales, lengths
FRACTION = Range(0, 1, high_open=True)  # [0, 1): dropout, a cropped share, Adam's betas
PROBABILITY = Range(0, 1, high_open=False)  # [0, 1]: thresholds on scores, ratios
FINITE = Range()  # any finite number
INTERVAL = Range(increasing=True)  # (low, high) of finite numbers


def range_problem(section: Any, name: str, value: Any) -> str | None:
    """What is wrong with `value` for the field `name` of the config dataclass `section` (its `Range`),
    or None (also for a field without one)."""
    hint = typing.get_type_hints(type(section), include_extras=True)[name]
    ranges = [item for item in getattr(hint, "__metadata__", ()) if isinstance(item, Range)]
    return next((problem for bounds in ranges if (problem := bounds.problem(value))), None)


def divisible(channels: int, channels_name: str, heads: int, heads_name: str) -> str | None:
    """Attention splits its channels into equal shares, one per head: a problem naming the two fields,
    or None."""
    if channels % heads:
        return (f"{channels_name} {channels} is not divisible by {heads_name} {heads} (each attention head "
                "takes an equal share of the channels)")  # fmt: skip
    return None


@dataclass
class EncoderConfig:
    """The shared BEV encoder: cameras (ResNet + FPN-like neck + GKT) and/or LiDAR pillars."""

    modality: Modality = "camera"
    x_range: Annotated[tuple[float, float], INTERVAL] = (-15.0, 15.0)  # metres, BEV columns (x right)
    # metres, BEV rows (y forward; row 0 = front)
    y_range: Annotated[tuple[float, float], INTERVAL] = (-30.0, 30.0)
    bev_h: Annotated[int, AT_LEAST_1] = 200  # rows: 60 m / 0.3 m
    bev_w: Annotated[int, AT_LEAST_1] = 100  # columns: 30 m / 0.3 m
    channels: Annotated[int, AT_LEAST_1] = 256
    dropout: Annotated[float, FRACTION] = 0.1
    # Camera branch.
    backbone: BackboneName = "resnet50"
    backbone_width: Annotated[int, AT_LEAST_1] = 64  # 64 is torchvision's; pretrained weights need 64
    backbone_weights: str = ""  # local torchvision state_dict file; never downloaded
    # as mmdet's: -1 none, 0 the stem, 1 the stem and layer1 (MapTR's)
    backbone_frozen_stages: Annotated[int, Range(-1, 4, high_open=False)] = 1
    backbone_norm_eval: bool = True  # keep pretrained BatchNorm statistics
    # the neck's output stride: 4, 8, 16 or 32 (the neck names them; the range catches the rest early)
    feature_stride: Annotated[int, Range(4, 32, high_open=False)] = 32
    # Heights above the ground of the 3D points of a BEV pillar: each frame's ground plane moves them into
    # its BEV frame, z = ground_z + a x + b y + height (frames.ground_z: about -1.84 in nuScenes' LIDAR_TOP
    # frame, -0.33 under AV2's rear axle; frames.ground_slope (a, b): about (0.006, 0.024) in nuScenes', whose
    # LIDAR_TOP is pitched on the ego, (0, 0) in AV2's).
    camera_heights: Annotated[tuple[float, ...], FINITE] = (-1.5, -0.5, 0.5, 1.5)
    # GKT kernel (rows, columns) around each projection
    kernel_size: Annotated[tuple[int, int], AT_LEAST_1] = (3, 5)
    camera_heads: Annotated[int, AT_LEAST_1] = 4
    camera_layers: Annotated[int, AT_LEAST_1] = 1
    max_views: Annotated[int, AT_LEAST_1] = 2  # cameras a BEV point reads at most (overlaps are seen by two)
    # LiDAR branch.
    pillar_channels: Annotated[int, AT_LEAST_1] = 64
    # pillars per BEV cell side (2: 0.15 m pillars on the 0.3 m grid)
    pillar_subdivision: Annotated[int, AT_LEAST_1] = 2
    # metres above the ground; points outside are dropped
    z_range: Annotated[tuple[float, float], INTERVAL] = (-5.0, 3.0)
    lidar_blocks: Annotated[int, AT_LEAST_0] = 2

    def problem(self) -> str | None:
        """What the camera branch's build would assert, naming the fields; None when it builds."""
        if self.modality == "lidar":
            return None
        if self.feature_stride not in (4, 8, 16, 32):
            stride = self.feature_stride
            return f"encoder.feature_stride must be 4, 8, 16 or 32 (a stage of the backbone), not {stride}"
        return divisible(self.channels, "encoder.channels", self.camera_heads, "encoder.camera_heads")

    def metres_to_unit(self, xy: Any) -> Any:
        """BEV metres (..., 2) -> unit coordinates (u right, v down the rows; (0, 0) = front-left corner)."""
        (x0, x1), (y0, y1) = self.x_range, self.y_range
        u = (xy[..., 0] - x0) / (x1 - x0)
        v = (y1 - xy[..., 1]) / (y1 - y0)
        return _stack(u, v, xy)

    def unit_to_metres(self, uv: Any) -> Any:
        (x0, x1), (y0, y1) = self.x_range, self.y_range
        return _stack(x0 + uv[..., 0] * (x1 - x0), y1 - uv[..., 1] * (y1 - y0), uv)

    def polyline_to_metres(self, uv: np.ndarray) -> np.ndarray:
        """A predicted (n, 2) unit polyline -> float64 metres inside the map: the decoders regress a
        little beyond the map's edge (so that lanes reach it), and the ground truth stops there."""
        inside = np.clip(np.asarray(uv, np.float64), 0.0, 1.0)
        moved = np.r_[True, np.any(inside[1:] != inside[:-1], axis=1)]  # points clipped onto one spot
        return self.unit_to_metres(inside[moved])


def _stack(a: Any, b: Any, like: Any) -> Any:
    # The same arithmetic serves numpy arrays (data, evaluation) and tensors (model).
    return torch.stack([a, b], -1) if isinstance(like, torch.Tensor) else np.stack([a, b], -1)


@dataclass
class DataConfig:
    """How samples are read. The image settings come twice: for real nuScenes / AV2 and for the synthetic
    data of `cli synth` (its images are already 1/4 and 1/8 of the real sizes, its cameras look level);
    the loader picks by the dataset's sensor root (pipeline/manifest.py `is_synthetic`). They are per rig:
    OpenLane-V2's frames take AV2's (subset A, the seven ring cameras) or nuScenes' (subset B, the six
    CAM_ cameras) by their cameras (baselines/data.py camera_rig)."""

    image_scale_nuscenes: Annotated[float, POSITIVE] = 0.5  # image resize ratio of the paper, on real data
    image_scale_av2: Annotated[float, POSITIVE] = 0.3
    # fraction of each image's height cut off its top after the resize (real data: none, as the paper)
    image_crop_top: Annotated[float, FRACTION] = 0.0
    # the synthetic images: nuScenes 400 x 225 and AV2 256 x 194 as written; smaller AV2 images lose lanes
    # (docs/EXPERIMENTS.md, 2026-12-02), and the top 40 % is sky above the level cameras' horizon, where no
    # point of the BEV grid projects (tests/test_camera_geometry.py): cropping it costs nothing
    synthetic_image_scale_nuscenes: Annotated[float, POSITIVE] = 0.5
    synthetic_image_scale_av2: Annotated[float, POSITIVE] = 1.0
    synthetic_image_crop_top: Annotated[float, FRACTION] = 0.4
    image_divisor: Annotated[int, AT_LEAST_1] = 32  # images are padded to a multiple of this (bottom / right)
    max_points: Annotated[int, AT_LEAST_1] = 120_000  # LiDAR points kept per sweep (random subset beyond)
    sensor_root: str = ""  # raw dataset root; default: the `root` in the prepared manifest.json
    cache_samples: bool = False  # keep decoded samples in memory (small datasets, many epochs)
    # loader processes (persistent over epochs), at most one per core
    num_workers: Annotated[int, AT_LEAST_0] = 4

    def image_settings(self, rig: Rig, synthetic: bool) -> tuple[float, float]:
        """(resize ratio, fraction of the height cut off the top) of the images of `rig`'s cameras."""
        if rig not in ("nuscenes", "av2"):
            raise ValueError(f"no image settings for the camera rig {rig!r} (nuscenes or av2)")
        if synthetic:
            nuscenes, av2 = self.synthetic_image_scale_nuscenes, self.synthetic_image_scale_av2
            return (nuscenes if rig == "nuscenes" else av2), self.synthetic_image_crop_top
        scale = self.image_scale_nuscenes if rig == "nuscenes" else self.image_scale_av2
        return scale, self.image_crop_top


# The paper's schedules (its implementation details, Tab. 11-12): 110 epochs on nuScenes, 24 on AV2; on
# OpenLane-V2 the 24 that TopoNet trains (the paper's OpenLane-V2 table, tab:toponet, sets LaneGAP beside it).
PAPER_EPOCHS = {"nuscenes": 110, "av2": 24, "openlanev2": 24}
# The prepared datasets without LiDAR (OpenLane-V2 ships camera images only): cli train takes the camera
# modality on them and refuses the others.
WITHOUT_LIDAR = frozenset({"openlanev2"})


@dataclass
class TrainConfig:
    # 0: the prepared dataset's schedule (PAPER_EPOCHS); run.json says which
    epochs: Annotated[int, AT_LEAST_0] = 0
    # the effective batch: over all processes and accumulated micro-batches
    batch_size: Annotated[int, AT_LEAST_1] = 32
    # frames one process holds in one forward pass (0: no cap). A batch above it per process is split
    # into `accumulate` micro-batches whose gradients add up before one optimiser step, so that one GPU
    # runs the paper's 32 as 8 processes of 4 do.
    max_batch_per_device: Annotated[int, AT_LEAST_0] = 0
    # micro-batches per optimiser step; 0: the fewest under max_batch_per_device
    accumulate: Annotated[int, AT_LEAST_0] = 0
    lr: Annotated[float, POSITIVE] = 6e-4
    backbone_lr_mult: Annotated[float, AT_LEAST_0] = 0.1  # 0: the backbone stays as it starts
    betas: Annotated[tuple[float, float], FRACTION] = (0.9, 0.999)
    eps: Annotated[float, POSITIVE] = 1e-8
    weight_decay: Annotated[float, AT_LEAST_0] = 0.01
    warmup_iters: Annotated[int, AT_LEAST_0] = 500
    warmup_ratio: Annotated[float, PROBABILITY] = 1.0 / 3  # warm-up starts at lr * warmup_ratio
    min_lr_ratio: Annotated[float, PROBABILITY] = 1e-3  # cosine decays to lr * min_lr_ratio
    # inf: no clipping
    grad_clip: Annotated[float, Range(low=0, low_open=True, high_open=False, infinite=True)] = 35.0
    amp: bool = True  # mixed precision on CUDA
    # numpy's seeds are 32-bit and non-negative; each process adds its rank
    seed: Annotated[int, Range(0, 2**31 - 1, high_open=False)] = 0
    log_every: Annotated[int, AT_LEAST_1] = 10
    threads: Annotated[int, AT_LEAST_0] = 0  # torch CPU threads; 0 keeps torch's default
    train_split: str = "train"
    val_split: str = "val"
    # Validation during training (val.jsonl, best.pt): every eval_every epochs and after the last one (0:
    # after the last one only), on eval_frames frames of val_split drawn once by the seed (0: all of them).
    eval_every: Annotated[int, AT_LEAST_0] = 1
    eval_frames: Annotated[int, AT_LEAST_0] = 0
    best_metric: BestMetric = "directed_junction_topo_f1"  # the paper's headline
    # optimiser steps between checkpoints inside an epoch (0: at epoch ends only)
    checkpoint_every: Annotated[int, AT_LEAST_0] = 0
    # non-finite steps in a row that stop the run (0: never stop); fp16 overflows count once the loss scale
    # is down to 1 (baselines/train.py)
    max_bad_steps: Annotated[int, AT_LEAST_0] = 10

    def micro_batches(self, world_size: int) -> tuple[int, int]:
        """(frames per forward pass, micro-batches per optimiser step) of each of `world_size` processes;
        a batch size that does not split evenly is a ValueError naming the options."""
        if self.batch_size % world_size:
            raise ValueError(f"--batch-size {self.batch_size} is not divisible by {world_size} processes")
        per_process = self.batch_size // world_size
        accumulate = self.accumulate
        if not accumulate:
            cap = self.max_batch_per_device or per_process
            splits = (k for k in range(1, per_process + 1) if per_process % k == 0)
            accumulate = next(k for k in splits if per_process // k <= cap)
        if per_process % accumulate:
            raise ValueError(f"--accumulate {accumulate}: the batch of {per_process} frames per process "
                             f"(--batch-size {self.batch_size} over {world_size} processes) does not split "
                             f"into {accumulate} equal micro-batches")  # fmt: skip
        return per_process // accumulate, accumulate

    def steps_per_epoch(self, frames: int, world_size: int) -> int:
        """The optimiser steps of an epoch over `frames` training frames, as baselines/train.py's loader
        makes them: each process's share (the sampler pads it to ceil(frames / world_size)) in
        micro-batches, the last smaller one dropped when the split holds a whole batch, `accumulate` of
        them a step (the last may hold fewer)."""
        micro_batch, accumulate = self.micro_batches(world_size)
        share = math.ceil(frames / world_size)
        batches = share // micro_batch if frames >= self.batch_size else math.ceil(share / micro_batch)
        return math.ceil(batches / accumulate)


@dataclass
class Config:
    preset: str = "paper"
    model: str = ""  # a key of baselines.models.MODELS
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    decoder: Any = None  # the model's head config (its own dataclass, baselines.models.HEADS)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        self.check_ranges()  # the presets and the model heads, as written in the code

    def check_ranges(self, where: str = "") -> None:
        """Every section's fields against their `Range`: the first one outside is a ValueError naming it
        (`where: train.max_bad_steps must be at least 0, not -1`)."""
        for section_field in dataclasses.fields(self):
            section = getattr(self, section_field.name)
            if not dataclasses.is_dataclass(section):
                continue
            for item in dataclasses.fields(section):
                problem = range_problem(section, item.name, getattr(section, item.name))
                if problem:
                    name = f"{section_field.name}.{item.name}"
                    raise ValueError(f"{where}: {name} {problem}" if where else f"{name} {problem}")
        self.check_across(where)

    def check_across(self, where: str = "") -> None:
        """What the model's build would assert of fields together (EncoderConfig.problem, the head
        config's `problem`): the first is a ValueError naming the fields (`where: encoder.channels ...`)."""
        problem = self.encoder.problem()
        if problem is None and self.decoder is not None:  # a model's head config
            problem = self.decoder.problem(self.encoder)
        if problem:
            raise ValueError(f"{where}: {problem}" if where else problem)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def save(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @staticmethod
    def from_dict(values: dict[str, Any], decoder: Any, source: str = "the saved config") -> Config:
        """`values` (a saved config, read from `source`) over the paper preset's sections and `decoder`, the
        head config of the model that `values` names (baselines.models.load_config); a value out of its
        field's range is an error naming `source` and the field."""
        config = Config(decoder=decoder)
        for key, value in values.items():
            if isinstance(value, dict):
                section = getattr(config, key)
                for name, item in value.items():
                    setattr(section, name, _coerce(getattr(section, name), item, f"{key}.{name}"))
            else:
                setattr(config, key, value)
        config.check_ranges(source)
        return config


def paper() -> Config:
    """The paper's settings (Tab. 11/12): ResNet-50 from ImageNet weights (`--pretrained`), 200 x 100 BEV,
    batch 32 (4 frames a forward pass: 8 GPUs' 4 each, or 8 accumulated micro-batches on one), 110
    epochs on nuScenes and 24 on AV2 and OpenLane-V2. The presets hold no model:
    baselines.models.resolve_config adds one and its head config."""
    return Config(
        preset="paper",
        encoder=EncoderConfig(),
        data=DataConfig(
            image_scale_nuscenes=0.5,
            image_scale_av2=0.3,
            image_crop_top=0.0,
            synthetic_image_scale_nuscenes=0.5,
            synthetic_image_scale_av2=1.0,
            synthetic_image_crop_top=0.4,
            cache_samples=False,
            num_workers=4,
        ),
        # validation every 4 epochs: under 10 % of the training time (docs/EXPERIMENTS.md, 2026-12-06)
        train=TrainConfig(epochs=0, batch_size=32, max_batch_per_device=4, eval_every=4),
    )


def tiny() -> Config:
    """A CPU-sized model: seconds per epoch on the synthetic data, the same code paths as `paper`."""
    return Config(
        preset="tiny",
        encoder=EncoderConfig(
            modality="fusion",  # the learning checks' recipe: paint in the images and the LiDAR intensities
            bev_h=40,
            bev_w=20,
            channels=64,
            dropout=0.0,
            backbone="resnet18",
            backbone_width=16,
            backbone_frozen_stages=-1,  # nothing frozen: no pretrained weights
            backbone_norm_eval=False,
            feature_stride=8,
            camera_heights=(0.0,),  # the ground itself (lane paint), on both datasets
            kernel_size=(3, 3),
            camera_heads=4,
            max_views=2,
            pillar_channels=32,
            pillar_subdivision=1,
            lidar_blocks=1,
        ),
        data=DataConfig(
            # real data at 1/8 of its size, as large as the synthetic images are
            image_scale_nuscenes=0.125,
            image_scale_av2=0.125,
            image_crop_top=0.0,
            synthetic_image_scale_nuscenes=0.5,  # 200 x 113
            synthetic_image_scale_av2=1.0,  # 256 x 194
            synthetic_image_crop_top=0.4,
            # max_points stays the default's 120,000, more than a synthetic sweep holds in the BEV range: a
            # random 20,000 lost most of the paint's returns (docs/EXPERIMENTS.md, 2026-12-04)
            num_workers=0,
            cache_samples=True,
        ),
        # batch 2, 11 epochs (880 steps): more, smaller steps learn more within the learning checks' CPU
        # budget (docs/EXPERIMENTS.md, 2026-12-02).
        train=TrainConfig(
            epochs=11, batch_size=2, lr=2e-3, backbone_lr_mult=1.0, warmup_iters=50, amp=False, threads=2
        ),
    )


def gpu() -> Config:
    """One CUDA GPU (`make gpu-check`): the paper's 0.3 m BEV cells (and decoder sizes), a ResNet-18
    camera branch (no pretrained weights can be had there), bf16 autocast, one schedule for every model;
    the paper's image scales on real data, the synthetic images as written; loader workers, no cache."""
    return Config(
        preset="gpu",
        encoder=EncoderConfig(
            modality="fusion",
            bev_h=200,
            bev_w=100,
            channels=256,
            backbone="resnet18",
            backbone_frozen_stages=-1,  # nothing frozen: no pretrained weights
            backbone_norm_eval=False,
            feature_stride=8,
            camera_heights=(0.0,),
            kernel_size=(3, 3),
            max_views=2,
        ),
        data=DataConfig(
            image_scale_nuscenes=0.5,
            image_scale_av2=0.3,
            image_crop_top=0.0,
            synthetic_image_scale_nuscenes=0.5,
            synthetic_image_scale_av2=1.0,
            synthetic_image_crop_top=0.4,
            cache_samples=False,
            num_workers=8,
        ),
        train=TrainConfig(
            epochs=16, batch_size=8, lr=1e-3, backbone_lr_mult=1.0, warmup_iters=100, eval_every=4
        ),
    )


PRESETS = {"paper": paper, "tiny": tiny, "gpu": gpu}


def apply_overrides(config: Config, overrides: list[str], option: str = "--set") -> Config:
    """Apply `section.field=value` strings, each value parsed as its field's type; a bad one is an error
    naming `option` and the string (`--set train.epochs=abc: train.epochs expects an integer, ...`)."""
    for item in overrides:
        set_field(config, item, f"{option} {item}")
    config.check_across(option)  # the fields together, once all are set
    return config


def set_field(config: Config, item: str, where: str) -> None:
    """Apply one `section.field=value`; errors start with `where`."""
    name, sep, text = item.partition("=")
    section_name, dot, field_name = name.strip().partition(".")
    sections = [
        f.name for f in dataclasses.fields(config) if dataclasses.is_dataclass(getattr(config, f.name))
    ]
    if not sep or not dot:
        raise ValueError(f"{where}: expected section.field=value")
    if section_name not in sections:
        raise ValueError(f"{where}: no config section {section_name!r} (sections: {', '.join(sections)})")
    section = getattr(config, section_name)
    types = typing.get_type_hints(type(section))
    if field_name not in types:
        owner = f"the {config.model} model's " if section_name == "decoder" else ""
        raise ValueError(f"{where}: {owner}{section_name} has no field {field_name!r}")
    try:
        value = _parse(types[field_name], text.strip())
    except ValueError as expected:
        raise ValueError(f"{where}: {section_name}.{field_name} expects {expected}") from None
    problem = range_problem(section, field_name, value)
    if problem:
        raise ValueError(f"{where}: {section_name}.{field_name} {problem}")
    setattr(section, field_name, value)


def _parse(kind: Any, text: str) -> Any:
    """`text` as a value of the field type `kind`; a ValueError says what was expected."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is Literal:
        if text not in args:
            raise ValueError(f"one of {', '.join(args)}, not {text!r}")
        return text
    if kind is bool:
        if text.lower() not in ("true", "false", "1", "0"):
            raise ValueError(f"true or false, not {text!r}")
        return text.lower() in ("true", "1")
    if kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            raise ValueError(f"{'an integer' if kind is int else 'a number'}, not {text!r}") from None
    if origin is tuple:  # "3,5", "(3, 5)" and "3" all give a tuple
        parts = [part.strip() for part in text.strip("()[] ").split(",") if part.strip()]
        count = "" if Ellipsis in args else f"{len(args)} "
        expected = f"{count}{'integers' if args[0] is int else 'numbers'} separated by commas, not {text!r}"
        if count and len(parts) != len(args):
            raise ValueError(expected)
        try:
            return tuple(args[0](part) for part in parts)
        except ValueError:
            raise ValueError(expected) from None
    return text


def _coerce(current: Any, value: Any, name: str) -> Any:
    """`value` (a string from the command line, or a JSON value) as the type of `current`."""
    if isinstance(value, str) and not isinstance(current, str):
        if isinstance(current, bool):
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"{name}: expected true or false, got {value!r}")
            return value.lower() in ("true", "1")
        if isinstance(current, tuple):
            value = f"({value.strip('()[] ')},)"  # "3,5", "(3, 5)" and "3" all give a tuple
        value = ast.literal_eval(value)
    if isinstance(current, tuple):
        value = tuple(value)
        element = type(current[0]) if current else float
        return tuple(element(v) for v in value)
    if isinstance(current, bool):
        return bool(value)
    if isinstance(current, float):
        return float(value)
    if isinstance(current, int):
        return int(value)
    return value
