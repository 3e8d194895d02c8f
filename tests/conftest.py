"""Shared fixtures: the real AV2 fixtures in ../shared/data and datasets prepared from them."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
AV2_ROOT = SHARED_DATA / "av2" / "sensor"


def require_shared_av2() -> Path:
    if not AV2_ROOT.is_dir():
        pytest.skip(f"real AV2 fixtures not found at {AV2_ROOT} (../shared/data beside the repo)")
    return AV2_ROOT


@pytest.fixture(scope="session")
def av2_root() -> Path:
    return require_shared_av2()


@pytest.fixture(scope="session")
def prepared_av2(av2_root, tmp_path_factory) -> Path:
    """The real AV2 logs prepared with the default options."""
    from pipeline.prepare import prepare
    from pipeline.targets import TargetOptions

    out = tmp_path_factory.mktemp("prepared_av2")
    prepare("av2", av2_root, out, TargetOptions())
    return out
