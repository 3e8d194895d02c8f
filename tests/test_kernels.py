"""The kernels' ahead-of-time build (pipeline/kernels.py, tools/build_kernels.py): `cli score` under it gives
the JIT's scores to the last digit without importing numba; a call of other argument types, a stale build or
LANEGRAPH_JIT=1 runs under numba.

`make test` builds the kernels first (where a C compiler is) and then sets LANEGRAPH_AOT_REQUIRED=1: there a
stale build fails instead of skipping."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from benchmark.graph_table import graph_row, graphs_from_table, read_graph_table
from benchmark.metric import densify
from pipeline import kernels
from pipeline.lane_graph import LaneGraph

REPO = Path(__file__).resolve().parents[1]


def require_build() -> None:
    status = kernels.aot_status()
    if not status.startswith("used"):
        if os.environ.get("LANEGRAPH_AOT_REQUIRED") == "1":
            pytest.fail(f"the kernels' ahead-of-time build is {status}")
        pytest.skip(f"the kernels' ahead-of-time build is {status}")


@pytest.fixture
def fresh_status(monkeypatch):
    """pipeline.kernels reads its build again in the test, and again after it."""
    kernels._load.cache_clear()
    yield monkeypatch
    monkeypatch.undo()
    kernels._load.cache_clear()


def test_argument_types_tell_apart_what_numba_types_apart():
    """Two arguments that select the same compiled version must be typed alike by numba: else a version
    would run on memory it does not expect."""
    import numba

    read_only = np.zeros(3)
    read_only.flags.writeable = False
    values = [
        np.zeros(3), np.zeros(3, np.float32), np.zeros(3, np.int64), np.zeros(3, np.int32),
        np.zeros(3, np.bool_), np.zeros((2, 3)), np.zeros((3, 2)).T, np.zeros(6)[::2],
        np.zeros((4, 4))[:, :2], read_only, np.zeros((2, 2, 2)), 1, 2**40, 1.5, True, False, np.int32(3),
        np.int64(2), np.float32(1.0), np.float64(2.0), np.bool_(True), np.uint8(1),
    ]  # fmt: skip
    typed: dict = {}
    for value in values:
        (described,) = kernels.argument_types((value,))
        assert typed.setdefault(described, numba.typeof(value)) == numba.typeof(value), value
    assert len(typed) == 17  # 11 kinds of array, 6 of scalar
    assert kernels.argument_types(("text", [1], None)) == (None, None, None)


def score_process(pred: Path, gt: Path, out: Path, jit: bool) -> dict:
    """`cli score` under every metric in a fresh process: its result, and whether numba was imported."""
    script = (
        "import json, sys; from typer.main import get_command; import cli; "
        "get_command(cli.app).main(sys.argv[1:], standalone_mode=False); "
        "from pipeline.kernels import aot_status; "
        "print(json.dumps({'numba': 'numba' in sys.modules, 'status': aot_status()}))"
    )
    args = ["score", "--pred", str(pred), "--gt", str(gt), "--metric", "lanegap,cgnet,openlanev2"]
    env = {**os.environ, "LANEGRAPH_JIT": "1" if jit else "0"}
    run = subprocess.run(
        [sys.executable, "-c", script, *args, "--out", str(out)], cwd=REPO, env=env, capture_output=True,
        text=True, check=True,
    )  # fmt: skip
    return {**json.loads(run.stdout.strip().splitlines()[-1]), "result": json.loads(out.read_text())}


def test_cli_score_under_the_build_equals_the_jit_without_numba(synth_prepared, tmp_path):
    require_build()
    gt = synth_prepared["av2"]
    rng = np.random.default_rng(3)
    rows = []
    for frame_id, g in sorted(graphs_from_table(read_graph_table(gt), gt).items()):
        keep = rng.random(len(g.src)) >= 0.15
        dx, dy = rng.normal(0.0, 0.2, (2, len(g.x))).astype(np.float32)
        rows.append(graph_row(frame_id, LaneGraph(g.x + dx, g.y + dy, g.src[keep], g.dst[keep])))
    pq.write_table(pa.Table.from_pylist(rows), tmp_path / "pred.parquet")
    built = score_process(tmp_path / "pred.parquet", gt, tmp_path / "aot.json", jit=False)
    jit = score_process(tmp_path / "pred.parquet", gt, tmp_path / "jit.json", jit=True)
    assert built["status"].startswith("used") and not built["numba"]
    assert jit["status"] == "not used: LANEGRAPH_JIT=1" and jit["numba"]
    assert built["result"] == jit["result"]
    assert 0.3 < built["result"]["cgnet"]["topo"]["f1"] < 1.0


def test_a_call_of_types_the_build_lacks_runs_under_numba_alike():
    require_build()
    rng = np.random.default_rng(0)
    xy = np.round(rng.uniform(0, 5, (400, 2)), 0)  # many equal points
    order = np.argsort(xy[:, 0])
    table = kernels._aot()[densify._identical_points.key]
    assert kernels.argument_types((xy, order.copy())) in table
    strided = np.asfortranarray(xy)
    assert kernels.argument_types((strided, order.copy())) not in table
    built = densify._identical_points(xy, order.copy())
    jit = densify._identical_points(strided, order.copy())
    assert built[1] == jit[1] < 40 and np.array_equal(built[0], jit[0])


def test_a_build_of_other_sources_or_numpy_is_not_used(fresh_status, tmp_path):
    index = tmp_path / "index.json"
    fresh_status.setattr(kernels, "AOT_INDEX", index)
    assert kernels.aot_status().startswith("not built")
    sources = kernels.source_hashes()
    first = sorted(sources)[0]
    index.write_text(json.dumps({"numpy": np.__version__, "sources": {**sources, first: "0"}, "kernels": {}}))
    kernels._load.cache_clear()
    assert kernels.aot_status().startswith(f"stale: {first} is not the build's source")
    index.write_text(json.dumps({"numpy": "1.0", "sources": sources, "kernels": {}}))
    kernels._load.cache_clear()
    assert kernels.aot_status() == f"stale: built for numpy 1.0, not {np.__version__}"
    assert kernels._aot() == {}


def test_a_kernel_pickles_by_name():
    import pickle

    assert pickle.loads(pickle.dumps(densify._identical_points)) is densify._identical_points


@pytest.fixture(scope="module")
def small_build(tmp_path_factory):
    """tools/build_kernels.py's main into a folder of its own, its workload one kernel call: a real
    compiled module and its index, beside two earlier modules (this Python's and another's) and a file of
    another name. Needs a C compiler, as `make kernels` does."""
    import shutil

    from tools import build_kernels

    if shutil.which("cc") is None:
        pytest.skip("no C compiler (cc): the kernels' build needs one")
    folder = tmp_path_factory.mktemp("build")
    strays = [folder / f"{kernels.AOT_NAME}.cpython-312-x86_64-linux-gnu.so",
              folder / f"{kernels.AOT_NAME}{kernels.importlib.machinery.EXTENSION_SUFFIXES[0]}"]  # fmt: skip
    for stray in strays:
        stray.write_bytes(b"an earlier build")
    (folder / "kernels.py").write_text("kept")
    xy = np.round(np.random.default_rng(0).uniform(0, 5, (400, 2)), 0)
    order = np.argsort(xy[:, 0])
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(kernels, "AOT_INDEX", folder / f"{kernels.AOT_NAME}.json")
        patch.setattr(kernels, "_RECORDED", None)  # the build records calls; restored after it
        patch.setattr(build_kernels, "workload", lambda tmp: densify._identical_points(xy, order))
        build_kernels.main()
    return folder


def test_a_rebuild_removes_every_earlier_module_and_its_index_names_the_new_one(small_build, fresh_status):
    index = json.loads((small_build / f"{kernels.AOT_NAME}.json").read_text())
    module = small_build / f"{kernels.AOT_NAME}{kernels.importlib.machinery.EXTENSION_SUFFIXES[0]}"
    assert index.get("module", {}).get("file") == module.name
    assert sorted(p.name for p in small_build.iterdir()) == sorted(
        [module.name, f"{kernels.AOT_NAME}.json", "kernels.py"]
    )
    assert module.read_bytes() != b"an earlier build"
    assert index["module"]["sha256"] == kernels.hashlib.sha256(module.read_bytes()).hexdigest()
    fresh_status.setattr(kernels, "AOT_INDEX", small_build / f"{kernels.AOT_NAME}.json")
    assert kernels.aot_status() == "used: 1 versions of 1 kernels"
    xy = np.round(np.random.default_rng(1).uniform(0, 5, (300, 2)), 0)
    order = np.argsort(xy[:, 0])
    built = kernels._aot()[densify._identical_points.key][kernels.argument_types((xy, order))]
    same, jit = built(xy, order.copy()), densify._identical_points.dispatcher(xy, order.copy())
    assert same[1] == jit[1] and np.array_equal(same[0], jit[0])


@pytest.fixture
def loads(fresh_status):
    """Every extension module loaded from now on (its path), whichever way it is imported."""
    from importlib.machinery import ExtensionFileLoader

    loaded: list[str] = []
    create = ExtensionFileLoader.create_module
    fresh_status.setattr(ExtensionFileLoader, "create_module", lambda self, spec: loaded.append(self.path)
                         or create(self, spec))  # fmt: skip
    fresh_status.delitem(sys.modules, f"pipeline.{kernels.AOT_NAME}", raising=False)
    return loaded


def copy_build(build: Path, to: Path, monkeypatch) -> tuple[Path, dict]:
    """The small build in a folder of its own, its index the one pipeline.kernels reads, and the folder on
    the package's import path as if beside pipeline/kernels.py: its module's path and its index."""
    import shutil

    import pipeline

    shutil.copytree(build, to)
    monkeypatch.setattr(kernels, "AOT_INDEX", to / f"{kernels.AOT_NAME}.json")
    monkeypatch.setattr(pipeline, "__path__", [str(to), *pipeline.__path__])
    module = to / f"{kernels.AOT_NAME}{kernels.importlib.machinery.EXTENSION_SUFFIXES[0]}"
    return module, json.loads(kernels.AOT_INDEX.read_text())


def test_a_module_whose_digest_differs_from_the_index_is_not_loaded(small_build, loads, fresh_status,
                                                                     tmp_path):  # fmt: skip
    module, index = copy_build(small_build, tmp_path / "build", fresh_status)
    module.write_bytes(module.read_bytes() + b"\0")  # still a loadable module, but not the build's
    assert kernels.aot_status() == (
        f"not used: {module.name} is not the module the build made (its sha256 differs); `make kernels`"
    )
    assert kernels._aot() == {} and loads == []


def test_a_module_the_index_does_not_name_is_never_loaded(small_build, loads, fresh_status, tmp_path):
    """A loadable module beside the index and on the package's import path: neither an index that names no
    module, nor one that names another file (absent, elsewhere or of another Python) loads it."""
    module, index = copy_build(small_build, tmp_path / "build", fresh_status)
    index_path = kernels.AOT_INDEX
    other = tmp_path / "other"
    other.mkdir()
    (other / module.name).write_bytes(module.read_bytes())
    unnamed = {key: value for key, value in index.items() if key != "module"}
    digest = kernels.hashlib.sha256(module.read_bytes()).hexdigest()
    absent = {"file": f"{kernels.AOT_NAME}.abi3.so", "sha256": digest}
    elsewhere = {"file": f"../other/{module.name}", "sha256": digest}
    another_python = {"file": f"{kernels.AOT_NAME}.cpython-312-x86_64-linux-gnu.so", "sha256": digest}
    for written, status in (
        (unnamed, f"not used: {index_path.name} names no compiled module; `make kernels`"),
        ({**index, "module": absent},
         f"not built ({kernels.AOT_NAME}.abi3.so absent or unreadable): `make kernels`"),
        ({**index, "module": elsewhere},
         f"not used: {index_path.name} names '{elsewhere['file']}', not a module of this Python beside it"),
        ({**index, "module": another_python},
         f"not used: {index_path.name} names '{kernels.AOT_NAME}.cpython-312-x86_64-linux-gnu.so', not a "
         "module of this Python beside it"),
    ):  # fmt: skip
        index_path.write_text(json.dumps(written))
        kernels._load.cache_clear()
        assert kernels.aot_status() == status
        assert loads == []
