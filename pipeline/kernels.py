"""The project's compiled kernels: numba nopython functions that need not import numba to run.

`@kernel` (or `@kernel(inline="always")`) marks a numba kernel, compiled with `cache=True` as `numba.njit`
would. Importing a module of kernels does not import numba: numba's import and the start of its compiler,
even for cached kernels, are most of a one-frame `cli score`. A call runs the ahead-of-time build
of the kernel (`make kernels`, which `make test` runs: pipeline/_aot_kernels.*.so and its
.json) when that build was made from these very sources and holds the call's argument types; any other call
imports numba and compiles as before. The index (.json) names the one compiled module of the build and its
sha256: only that file is loaded, and only when its bytes are the build's; any other file beside it is not.
Both are numba's code generation of the same source; tests/test_kernels.py holds them equal.
LANEGRAPH_JIT=1 never uses the build.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.machinery
import importlib.util
import json
import os
from pathlib import Path

import numpy as np

AOT_NAME = "_aot_kernels"  # the extension module, beside this file
AOT_INDEX = Path(__file__).with_name(AOT_NAME + ".json")
SOURCE_PACKAGES = ("pipeline", "benchmark")  # the build's sources: every module here, hashed


class Kernel:
    """A numba kernel: the Python function, numba's dispatcher made on first need, and its ahead-of-time
    versions by argument types."""

    def __init__(self, py_func, options: dict):
        functools.update_wrapper(self, py_func)
        self.py_func = py_func
        self.options = options
        self.key = f"{py_func.__module__}.{py_func.__qualname__}"
        self._dispatcher = None

    @property
    def dispatcher(self):
        """numba's dispatcher of this kernel (this imports numba)."""
        if self._dispatcher is None:
            numba = _numba()
            self._dispatcher = numba.njit(cache=True, **self.options)(self.py_func)
        return self._dispatcher

    def __reduce__(self):  # pickled by name, as the function it wraps would be
        return _named, (self.__module__, self.__qualname__)

    def __call__(self, *args):
        if _RECORDED is not None:
            return _record(self, args)
        compiled = _aot().get(self.key)
        if compiled:
            fn = compiled.get(argument_types(args))
            if fn is not None:
                return fn(*args)
        return self.dispatcher(*args)


def _named(module: str, qualname: str) -> Kernel:
    return getattr(importlib.import_module(module), qualname)


def kernel(py_func=None, **options):
    """`@kernel` or `@kernel(inline="always")`: a numba kernel (options as numba.njit's)."""
    if py_func is None:
        return lambda f: Kernel(f, options)
    return Kernel(py_func, options)


def argument_types(args: tuple) -> tuple:
    """What selects an ahead-of-time version: per argument, what numba's typing of it depends on (an array's
    dtype, dimensions, layout, writability and alignment; a scalar's type); None where the build has none."""
    return tuple(_argument_type(a) for a in args)


def _argument_type(value):
    if isinstance(value, np.ndarray):
        flags = value.flags
        layout = "C" if flags.c_contiguous else "F" if flags.f_contiguous else "A"
        return ("array", value.dtype.str, value.ndim, layout, flags.writeable, flags.aligned)
    if isinstance(value, (bool, np.bool_)):
        return "bool"
    if isinstance(value, int) and -(2**63) <= value < 2**63:
        return "<i8"
    if isinstance(value, float):
        return "<f8"
    if isinstance(value, (np.integer, np.floating)):
        return value.dtype.str
    return None


_RECORDED: dict | None = None


def record_calls() -> dict:
    """From now on every kernel call runs under numba and is recorded, for tools/build_kernels.py: the
    returned {Kernel: {argument types: numba's types of the arguments}} fills as calls come."""
    global _RECORDED
    _RECORDED = {}
    return _RECORDED


def _record(k: Kernel, args: tuple):
    result = k.dispatcher(*args)
    types = argument_types(args)
    if None not in types:
        _RECORDED.setdefault(k, {})[types] = tuple(k.dispatcher.typeof_pyval(a) for a in args)
    return result


def source_hashes(root: Path | None = None) -> dict[str, str]:
    """sha256 of every module of the packages that hold kernels, by path under the repository root: a build
    whose sources differ is not used (numba freezes the globals a kernel reads, wherever they live)."""
    root = root or Path(__file__).resolve().parents[1]
    files = sorted(f for package in SOURCE_PACKAGES for f in (root / package).rglob("*.py"))
    return {f.relative_to(root).as_posix(): hashlib.sha256(f.read_bytes()).hexdigest() for f in files}


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes, as the index records its compiled module."""
    with path.open("rb") as file:
        return hashlib.file_digest(file, "sha256").hexdigest()


def compiled_modules(folder: Path) -> list[Path]:
    """Every compiled module of the build in `folder`, of this Python or any other: each file named
    _aot_kernels.* but the index."""
    return sorted(f for f in folder.glob(AOT_NAME + ".*") if f.name != AOT_NAME + ".json")


def aot_status() -> str:
    """Whether the ahead-of-time build is used, and why not, in one line."""
    return _load()[0]


def _aot() -> dict[str, dict[tuple, object]]:
    """key -> {argument types -> compiled function} of a build made from these sources; {} otherwise."""
    return _load()[1]


@functools.cache
def _load() -> tuple[str, dict[str, dict[tuple, object]]]:
    if os.environ.get("LANEGRAPH_JIT") == "1":
        return "not used: LANEGRAPH_JIT=1", {}
    try:
        index = json.loads(AOT_INDEX.read_text())
    except (OSError, ValueError):
        return f"not built ({AOT_INDEX.name} absent or unreadable): `make kernels`", {}
    if index.get("numpy") != np.__version__:
        return f"stale: built for numpy {index.get('numpy')}, not {np.__version__}", {}
    changed = sorted(set(index.get("sources", {}).items()) ^ set(source_hashes().items()))
    if changed:
        return f"stale: {changed[0][0]} is not the build's source; `make kernels`", {}
    record = index.get("module")
    if not (isinstance(record, dict) and isinstance(record.get("file"), str) and "sha256" in record):
        return f"not used: {AOT_INDEX.name} names no compiled module; `make kernels`", {}
    suffixes = importlib.machinery.EXTENSION_SUFFIXES
    if record["file"] not in {AOT_NAME + suffix for suffix in suffixes}:
        # a path elsewhere, or a module of another Python's or platform's suffix
        why = f"{AOT_INDEX.name} names {record['file']!r}, not a module of this Python beside it"
        return f"not used: {why}", {}
    path = AOT_INDEX.parent / record["file"]
    try:
        digest = file_digest(path)
    except OSError:
        return f"not built ({record['file']} absent or unreadable): `make kernels`", {}
    if digest != record["sha256"]:
        why = f"{record['file']} is not the module the build made (its sha256 differs)"
        return f"not used: {why}; `make kernels`", {}
    try:
        module = _load_module(path)
    except ImportError as error:
        return f"not loadable ({error})", {}
    table = {
        key: {_hashable(types): getattr(module, name) for types, name in versions}
        for key, versions in index["kernels"].items()
    }
    return f"used: {sum(map(len, table.values()))} versions of {len(table)} kernels", table


def _load_module(path: Path):
    """The extension module at exactly `path` (the import system would take whichever _aot_kernels.* it finds
    first on the package's path)."""
    name = f"{__package__}.{AOT_NAME}"
    loader = importlib.machinery.ExtensionFileLoader(name, str(path))
    spec = importlib.util.spec_from_file_location(name, path, loader=loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def _hashable(value):
    return tuple(_hashable(v) for v in value) if isinstance(value, list) else value


@functools.cache
def _numba():
    """numba, with Kernel objects typed as their dispatchers inside other kernels."""
    import numba
    from numba.extending import typeof_impl

    @typeof_impl.register(Kernel)
    def _typeof_kernel(value, context):
        return typeof_impl(value.dispatcher, context)

    return numba
