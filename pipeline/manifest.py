"""A prepared dataset opened once (`PreparedData`): what its manifest.json records and its frames' splits,
the handle that `cli train` and `cli eval` pass on; the stale-data check of its target parameters; the
check that `cli prepare` adds to a folder only under the options that made it; and the files of the folder
that `cli prepare` writes, which an --overwrite run replaces whole or not at all."""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from pipeline import io

# What defines a prepared dataset's targets: manifest.json "parameters" and its schema_version.
TARGET_PARAMETERS = ("bev_range", "path_points", "piece_points", "max_paths", "resolution", "line_width")

Crop = tuple[tuple[float, float], tuple[float, float]]

# the files a run writes besides the tables' shards (<split>__<log>.parquet)
MANIFEST, ERRORS, PICTURE = "manifest.json", "errors.jsonl", "splits.png"
# where an --overwrite run writes until all of it has succeeded, in OUT: the earlier output stays whole
# until then, and OUT is on the same file system, so the new files move in by rename
STAGE = ".overwrite"
# inside the stage while the new output moves in: the earlier output being set aside (ASIDE_PARTLY), then
# all of it (ASIDE, renamed from ASIDE_PARTLY once complete), so that an interruption at any point can be
# undone from what the folders hold (recover_overwrite)
ASIDE_PARTLY, ASIDE = ".earlier-partly", ".earlier"
# manifest parameters that another run need not match: --split picks what to add, and the names' digest
# follows from the contents' (split_file_sha256), which are compared (and absent from older manifests)
NOT_COMPARED = ("split", "split_file_names_sha256")


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
    """A prepared dataset (docs/guide/prepare.md), its manifest read once: the folder, the dataset kind, the
    raw sensor root it was prepared from, the range it was cropped to and its target parameters."""

    path: Path
    manifest: dict = field(repr=False)

    @classmethod
    def open(cls, path: Path) -> PreparedData:
        return cls(Path(path), read_manifest(path))

    @property
    def kind(self) -> str | None:
        """"nuscenes", "av2" or "openlanev2" as the manifest records it; None without one."""
        return self.manifest.get("dataset")

    @property
    def has_annotated_lanes(self) -> bool:
        """OpenLane-V2 data: its frames keep their annotated lanes (io.read_annotated_lanes), their submission
        keys (io.read_openlanev2_keys) and no LiDAR."""
        return self.kind == "openlanev2"

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

    @property
    def frames_without_images(self) -> int:
        """The frames whose frame file names an image that is absent (OpenLane-V2's: a training run cannot
        read them); 0 for the other datasets, whose frames name only the images they have."""
        return int(self.manifest.get("frames_without_images", 0))

    def check_targets(self, trained: dict, what: str) -> None:
        refuse_stale(trained, self.targets, self.path, what)

    @cached_property
    def split_sizes(self) -> dict[str, int]:
        """{split: frames} of the `frames` table, read on first use."""
        splits = io.read_table(self.path, "frames", columns=["split"]).column("split").to_pylist()
        return {split: splits.count(split) for split in sorted(set(splits))}


def option_name(parameter: str) -> str:
    """The `cli prepare` option of a manifest parameter."""
    return {"bev_range": "--range", "split_files": "--split-file", "split_file_sha256": "--split-file"}.get(
        parameter, f"--{parameter.replace('_', '-')}"
    )


def shown(value) -> str:
    """A manifest parameter as the command line writes it."""
    if isinstance(value, dict):  # split files
        return ",".join(f"{name}={path}" for name, path in value.items())
    return "none" if value is None else str(value)


def recorded_version(dataset: str, version: str) -> str | None:
    """The --version a manifest records: nuScenes' table version; AV2 has none."""
    return version if dataset == "nuscenes" else None


def difference(key: str, old: dict, new: dict) -> str:
    """How a manifest's record `old` differs from this run's `new` at `key`, as the option that makes it."""
    if key == "split_file_sha256":  # the same paths (else their own difference says it), other contents
        return ", ".join(
            f"--split-file {name}={new['split_files'].get(name)} changed (sha256 {digest[:12]}, now "
            f"{new[key].get(name, '')[:12]})"
            for name, digest in old[key].items()
            if digest != new[key].get(name)
        )
    if key == "cities_sha256":  # OpenLane-V2's --cities: the same path (else its own difference says it)
        return f"--cities {new['cities']} changed (sha256 {str(old[key])[:12]}, now {str(new[key])[:12]})"
    return f"{option_name(key)} {shown(old.get(key))} (now {shown(new.get(key))})"


def check_manifest(
    out: Path, dataset: str, root: Path, version: str, parameters: dict, overwrite: bool
) -> None:
    """Refuse to add to a folder prepared from another raw dataset (--root, --version), with other
    options, split files whose contents changed or another schema version (unless `overwrite`): shards
    made otherwise must not be mixed with new ones. A manifest written before the split files' digests
    were recorded cannot vouch for their contents, and is refused when it names split files."""
    manifest_path = out / MANIFEST
    if not manifest_path.is_file() or overwrite:
        return
    before = read_manifest(out)
    old = {"dataset": before.get("dataset"), "root": before.get("root"), "version": before.get("version"),
           "split_scheme": "original", **before.get("parameters", {})}  # fmt: skip
    new = {"dataset": dataset, "root": str(root), "version": recorded_version(dataset, version), **parameters}
    differing = [key for key in {**old, **new} if key not in NOT_COMPARED and old.get(key) != new.get(key)]
    if "split_files" in differing or "split_file_sha256" not in old:
        differing = [key for key in differing if key != "split_file_sha256"]  # said by the paths, or unknown
    if "cities" in differing:
        differing = [key for key in differing if key != "cities_sha256"]
    if differing:
        changes = ", ".join(difference(key, old, new) for key in differing)
        raise ValueError(
            f"{out} was prepared with other options: {changes}; pass --overwrite or choose another --out"
        )
    if old.get("split_files") and "split_file_sha256" not in old:
        raise ValueError(
            f"{manifest_path}: records no digest of its --split-file contents (prepared by an earlier "
            f"version), so whether {shown(old['split_files'])} changed cannot be told; pass --overwrite to "
            "prepare it again, or choose another --out"
        )
    if before.get("schema_version") != io.SCHEMA_VERSION:
        raise ValueError(
            f"{manifest_path}: schema_version {before.get('schema_version')}, this version writes "
            f"{io.SCHEMA_VERSION}; pass --overwrite to prepare it again, or choose another --out"
        )


def written_files(folder: Path) -> list[Path]:
    """The files of `folder` that `cli prepare` writes, the manifest first: every table's shards
    (<split>__<log>.parquet), errors.jsonl, splits.png, manifest.json, and what an interrupted atomic write
    left (.<name>.tmp-<pid>). Nothing else: the user's own files in the folder are not ours to remove."""
    found = []
    for name in (MANIFEST, ERRORS, PICTURE):
        found += [folder / name] if (folder / name).is_file() else []
        found += sorted(folder.glob(f".{name}.tmp-*"))
    for table in io.ALL_TABLES:
        found += sorted((folder / table).glob("*__*.parquet"))
        found += sorted((folder / table).glob(".*__*.parquet.tmp-*"))
    return found


def remove_output(folder: Path) -> None:
    """Remove what `cli prepare` wrote in `folder` (written_files), then its table folders and itself if
    they are empty (what is left is not ours)."""
    for path in written_files(folder):
        path.unlink()
    for sub in [folder / table for table in io.ALL_TABLES] + [folder]:
        with contextlib.suppress(OSError):  # absent, or holding what is not ours
            sub.rmdir()


def move_files(source: Path, target: Path, manifest_last: bool = True) -> None:
    """Rename every file `cli prepare` wrote in `source` to the same place under `target`, the manifest
    last (first when setting an output aside): a folder with a manifest holds all of its output."""
    paths = written_files(source)
    for path in reversed(paths) if manifest_last else paths:
        moved = target / path.relative_to(source)
        moved.parent.mkdir(parents=True, exist_ok=True)
        os.replace(path, moved)


def move_in(stage: Path, out: Path) -> None:
    """The complete output of an --overwrite run (in `stage`) replaces everything earlier runs wrote in
    `out`; files the project did not write stay. The earlier files are set aside in the stage (all of
    them, then the folder is renamed ASIDE), the new ones moved in, the manifest last, and only then is the
    earlier output deleted: at every step recover_overwrite can put back the earlier output, or finish."""
    partly, aside = stage / ASIDE_PARTLY, stage / ASIDE
    partly.mkdir()
    move_files(out, partly, manifest_last=False)
    partly.rename(aside)
    move_files(stage, out)
    remove_output(aside)
    remove_output(stage)


def recover_overwrite(out: Path) -> str | None:
    """Undo what an --overwrite run that did not finish left in `out` (OUT/.overwrite), from the folders
    alone, and say what was done; None when nothing was left. Before moving in: its unfinished output is
    removed. While moving in: the earlier output is put back whole, and the new files removed. After its
    manifest moved in (only the clean-up unfinished): the new output stays, and the clean-up ends."""
    stage = out / STAGE
    if not stage.is_dir():
        return None
    partly, aside = stage / ASIDE_PARTLY, stage / ASIDE
    interrupted = "an interrupted `cli prepare --overwrite`"
    said = f"{out}: removed the unfinished output of {interrupted}"
    if aside.is_dir() and not written_files(stage):  # every new file, the manifest last, is in place
        said = f"{out}: finished the clean-up of {interrupted} (its output is whole)"
        remove_output(aside)
    if aside.is_dir():  # moving in was under way: every file of OUT's is new, the earlier ones all aside
        for path in written_files(out):
            path.unlink()
        aside.rename(partly)
    if partly.is_dir():  # the earlier files, all or some of them aside (the rest still in OUT)
        move_files(partly, out)
        remove_output(partly)
        said = f"{out}: put back the earlier output that {interrupted} was replacing"
    remove_output(stage)
    return said


def check_no_interrupted_overwrite(out: Path) -> None:
    """Refuse to add to a folder that an interrupted --overwrite run left (OUT/.overwrite): it may be
    part way through replacing the earlier output, which a run with --overwrite puts right first."""
    stage = out / STAGE
    if not stage.is_dir():
        return
    if (stage / ASIDE_PARTLY).is_dir() or (stage / ASIDE).is_dir():
        raise ValueError(
            f"{out}: an interrupted `cli prepare --overwrite` was replacing its output ({stage} is left); "
            "run with --overwrite, which first puts that right (the earlier output back, or the new one "
            "finished)"
        )
    raise ValueError(
        f"{out}: an interrupted `cli prepare --overwrite` left {stage} (the earlier output is whole); run "
        f"with --overwrite to start afresh, or delete {stage} to add to the earlier output"
    )
