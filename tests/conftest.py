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


@pytest.fixture(scope="session")
def synth_raw(tmp_path_factory) -> Path:
    """A small synthetic raw dataset (both formats), seed 0: 4 logs of 20 frames at 10 Hz in world 0, on its
    roundabout, fork, S-bend and a left turn (3 train, 1 val)."""
    from pipeline.synth import synth

    out = tmp_path_factory.mktemp("synth")
    synth(
        out,
        logs=4,
        frames_per_log=20,
        seed=0,
        frame_period=0.1,
        worlds=1,
        val_frames_per_log=20,
        val_frame_period=0.1,
    )
    return out


@pytest.fixture(scope="session")
def synth_prepared(synth_raw, tmp_path_factory) -> dict[str, Path]:
    """The synthetic dataset prepared from each format: {'av2': dir, 'nuscenes': dir}."""
    from pipeline.prepare import prepare
    from pipeline.targets import TargetOptions

    out = tmp_path_factory.mktemp("synth_prepared")
    prepare("av2", synth_raw / "av2" / "sensor", out / "av2", TargetOptions())
    prepare("nuscenes", synth_raw / "nuscenes", out / "nuscenes", TargetOptions(), version="v1.0-mini")
    return {"av2": out / "av2", "nuscenes": out / "nuscenes"}


def overfit_history(built, sensors, targets, steps: int, lr: float = 3e-3) -> list[dict[str, float]]:
    """The losses of `steps` Adam steps of a model's `Built` record on one fixed batch."""
    import torch

    optimiser = torch.optim.Adam(built.model.parameters(), lr=lr)
    history = []
    for _ in range(steps):
        losses = built.loss(built.model(sensors), targets)
        optimiser.zero_grad()
        losses["loss"].backward()
        optimiser.step()
        history.append({k: v.item() for k, v in losses.items()})
    return history


@pytest.fixture
def overfit():
    """`overfit_history`, for the models' "the loss falls when overfitting one batch" tests."""
    return overfit_history
