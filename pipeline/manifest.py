"""The stale-data check: a prepared dataset's target parameters, read from its manifest.json, against
those a model was trained on (recorded by `cli train` in run.json and by `cli eval` in predictions)."""

from __future__ import annotations

import json
from pathlib import Path

# What defines a prepared dataset's targets: manifest.json "parameters" and its schema_version.
TARGET_PARAMETERS = ("bev_range", "path_points", "piece_points", "max_paths", "resolution", "line_width")


def dataset_targets(data: Path) -> dict:
    """The target parameters of a prepared dataset (its manifest.json); {} for a graph-table file or a
    folder without manifest."""
    path = Path(data) / "manifest.json"
    if not path.is_file():
        return {}
    manifest = json.loads(path.read_text())
    parameters = manifest.get("parameters", {})
    targets = {key: parameters[key] for key in TARGET_PARAMETERS if key in parameters}
    if "schema_version" in manifest:
        targets["schema_version"] = manifest["schema_version"]
    return targets


def check_targets(trained: dict, data: Path, what: str) -> None:
    """Refuse a prepared dataset whose target parameters differ from those `what` was trained on."""
    current = dataset_targets(data)
    for key, value in trained.items():
        if key in current and current[key] != value:
            raise ValueError(
                f"{Path(data) / 'manifest.json'}: stale data: prepared with {key}={current[key]!r}, but "
                f"{what} was trained on {key}={value!r}; use a dataset prepared with the same options"
            )
