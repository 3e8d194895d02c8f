"""`prepare --executor ray` on a local Ray instance of 2 CPUs: every shard the same bytes as the local
executor's, the same manifest apart from the run's timings, the same errors; Ray stays out of `cli`."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.errors import DataError
from pipeline.prepare import prepare
from pipeline.targets import TargetOptions

REPO = Path(__file__).resolve().parents[1]
needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None, reason="ray is not installed (pip install -e '.[ray]')"
)
MEASURED = ("seconds", "frames_per_second", "peak_worker_mib")  # the run's timings and memory


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    """3 logs of 6 frames in both formats (2 train, 1 val), no sensors."""
    from pipeline.synth import synth

    out = tmp_path_factory.mktemp("synth_ray")
    synth(
        out,
        logs=3,
        frames_per_log=6,
        seed=1,
        sensors=False,
        frame_period=0.5,
        worlds=1,
        val_worlds=0,
        val_frames_per_log=6,
        val_frame_period=0.5,
    )
    return out


def root_of(raw: Path, dataset: str) -> Path:
    return raw / "av2" / "sensor" if dataset == "av2" else raw / "nuscenes"


def run(raw, dataset, out, **kw) -> dict:
    return prepare(dataset, root_of(raw, dataset), out, TargetOptions(), version="v1.0-mini", **kw)


def shard_bytes(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*.parquet"))}


def manifest(out: Path) -> dict:
    data = json.loads((out / "manifest.json").read_text())
    for key in MEASURED:
        data["last_run"].pop(key)
    return data


@needs_ray
@pytest.mark.parametrize("dataset", ["av2", "nuscenes"])
def test_ray_writes_the_local_bytes(raw, tmp_path, dataset):
    import ray

    local = run(raw, dataset, tmp_path / "local")
    remote = run(raw, dataset, tmp_path / "ray", executor="ray", workers=2)
    assert not ray.is_initialized()  # the executor shut down the instance it started
    assert local["frames"] == remote["frames"] == 18 and remote["peak_worker_mib"] > 0
    expected = shard_bytes(tmp_path / "local")
    assert len(expected) == 3 * 6  # 3 logs x 6 tables
    assert shard_bytes(tmp_path / "ray") == expected
    assert manifest(tmp_path / "ray") == manifest(tmp_path / "local")


@pytest.fixture
def ray_instance():
    """A local instance started here: the executor uses it as it is and leaves it running."""
    ray = pytest.importorskip("ray")
    ray.init("local", num_cpus=2, log_to_driver=False)
    yield ray
    ray.shutdown()


@needs_ray
def test_ray_bad_log_fails_with_its_file_or_is_skipped_as_locally(raw, tmp_path, ray_instance):
    root = tmp_path / "raw"
    shutil.copytree(raw / "av2" / "sensor", root / "av2" / "sensor")
    (bad,) = sorted((root / "av2" / "sensor" / "train").glob("*/map/log_map_archive_*.json"))[:1]
    bad.write_text(bad.read_text()[:2000])

    with pytest.raises(DataError, match=f"{bad.name}: vector map: cannot be read"):
        run(root, "av2", tmp_path / "fail", executor="ray", workers=2)
    assert ray_instance.is_initialized()

    run(root, "av2", tmp_path / "local", on_error="skip")
    summary = run(root, "av2", tmp_path / "ray", executor="ray", workers=2, on_error="skip")
    assert summary["frames"] == 12 and summary["frames_skipped"] == 6
    assert shard_bytes(tmp_path / "ray") == shard_bytes(tmp_path / "local")
    errors = [(tmp_path / out / "errors.jsonl").read_text() for out in ("local", "ray")]
    assert errors[0] == errors[1] and bad.name in errors[0]


def test_ray_missing_is_one_clear_error(raw, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    with pytest.raises(ImportError, match=r"pip install -e '\.\[ray\]'"):
        run(raw, "av2", tmp_path / "out", executor="ray")
    assert not (tmp_path / "out").exists()  # refused before any work


def test_cli_does_not_import_ray():
    code = "import sys, cli, pipeline.prepare; print('ray' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert result.stdout.strip() == "False", result.stderr
