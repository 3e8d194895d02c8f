"""A prepared dataset opened once (`PreparedData`): what its manifest.json records and its frames' splits,
the handle that `cli train` and `cli eval` pass on; and the stale-data check of its target parameters."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from pipeline import io

# What defines a prepared dataset's targets: manifest.json "parameters" and its schema_version.
TARGET_PARAMETERS = ("bev_range", "path_points", "piece_points", "max_paths", "resolution", "line_width")

Crop = tuple[tuple[float, float], tuple[float, float]]


def read_manifest(data: Path) -> dict:
    """A prepared dataset's manifest.json; {} for a graph-table file or a folder without one."""
    path = Path(data) / "manifest.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def targets_of(manifest: dict) -> dict:
    """The target parameters that a manifest records (the keys of TARGET_PARAMETERS and schema_version)."""
    parameters = manifest.get("parameters", {})
    targets = {key: parameters[key] for key in TARGET_PARAMETERS if key in parameters}
    if "schema_version" in manifest:
        targets["schema_version"] = manifest["schema_version"]
    return targets


def dataset_targets(data: Path) -> dict:
    """The target parameters of a prepared dataset (its manifest.json); {} for a graph-table file or a
    folder without manifest."""
    return targets_of(read_manifest(data))


def refuse_stale(trained: dict, current: dict, data: Path, what: str) -> None:
    """Refuse target parameters `current` of the dataset `data` that differ from those `what` was trained
    on."""
    for key, value in trained.items():
        if key in current and current[key] != value:
            raise ValueError(
                f"{Path(data) / 'manifest.json'}: stale data: prepared with {key}={current[key]!r}, but "
                f"{what} was trained on {key}={value!r}; use a dataset prepared with the same options"
            )


def check_targets(trained: dict, data: Path, what: str) -> None:
    """Refuse a prepared dataset whose target parameters differ from those `what` was trained on."""
    refuse_stale(trained, dataset_targets(data), data, what)


def is_synthetic(sensor_root: Path) -> bool:
    """Whether a raw dataset root was written by `cli synth` (its marker synth.json sits at the root of
    the output, the nuScenes root's parent and the AV2 sensor root's grandparent)."""
    from pipeline.synth import MARKER  # the writers behind it load only where a root is asked about

    root = Path(sensor_root).resolve()
    return any((folder / MARKER).is_file() for folder in (root, *root.parents[:2]))


@dataclass
class PreparedData:
    """A prepared dataset (docs/DATA.md), its manifest read once: the folder, the dataset kind, the raw
    sensor root it was prepared from, the range it was cropped to and its target parameters."""

    path: Path
    manifest: dict = field(repr=False)

    @classmethod
    def open(cls, path: Path) -> PreparedData:
        return cls(Path(path), read_manifest(path))

    @property
    def kind(self) -> str | None:
        """"nuscenes" or "av2" as the manifest records it; None without one."""
        return self.manifest.get("dataset")

    @property
    def sensor_root(self) -> Path:
        """The raw dataset the frames' sensor files are relative to (the folder itself without manifest)."""
        return Path(self.manifest.get("root", self.path))

    @property
    def crop(self) -> Crop | None:
        """(x_range, y_range) in metres that the dataset was cropped to, if recorded."""
        crop = self.manifest.get("range")
        return ((crop["x_min"], crop["x_max"]), (crop["y_min"], crop["y_max"])) if crop else None

    @property
    def bev_range(self) -> str:
        """The perception range the targets were cut to (cli prepare --range), 30x60 when not recorded."""
        return self.manifest.get("parameters", {}).get("bev_range", "30x60")

    @property
    def targets(self) -> dict:
        return targets_of(self.manifest)

    def check_targets(self, trained: dict, what: str) -> None:
        refuse_stale(trained, self.targets, self.path, what)

    @cached_property
    def split_sizes(self) -> dict[str, int]:
        """{split: frames} of the `frames` table, read on first use."""
        splits = io.read_table(self.path, "frames", columns=["split"]).column("split").to_pylist()
        return {split: splits.count(split) for split in sorted(set(splits))}
