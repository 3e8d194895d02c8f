"""Every tensor a model or its loss reads during a training step sits on the training device.

No GPU here, so the trainer is set up on a second device type, `meta` (shapes only, no data), the way
`cli train` sets it up on CUDA (baselines.train.setup); one step then runs under a dispatch mode that
records every operation whose tensor inputs sit on more than one device. A buffer left on the CPU (the
piece losses' extent, STSU's Bezier inverse) shows as such an operation, or as meta's own error. The
camera modality: the LiDAR pillars' scatter needs the data's values, which meta tensors lack; the
Hungarian matching (scipy, on the CPU by design) becomes the identity matching.
"""

from __future__ import annotations

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

import baselines.models.lanegap
import baselines.models.piecewise
import baselines.train
from baselines.models import resolve_config
from baselines.train import setup
from pipeline.manifest import PreparedData


class MixedDevices(TorchDispatchMode):
    """Records the operations whose tensor inputs (beyond 0-d scalars, which CUDA takes from the CPU too)
    sit on more than one device."""

    def __init__(self):
        super().__init__()
        self.mixed: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        inputs, _ = tree_flatten((args, kwargs or {}))
        devices = {t.device for t in inputs if isinstance(t, torch.Tensor) and t.dim() > 0}
        if len(devices) > 1:
            self.mixed.append(f"{func} on {sorted(map(str, devices))}")
        return func(*args, **(kwargs or {}))


def identity_matching(logits, points, targets, *args, **kwargs):
    """match_layers without scipy: query i to target i, on the logits' device."""
    device = logits.device
    return [[(torch.arange(len(t), device=device),) * 2 for t in targets] for _ in range(logits.shape[0])]


@pytest.mark.parametrize("model", ["lanegap", "maptr", "stsu", "hdmapnet"])
def test_a_training_step_reads_only_tensors_on_the_training_device(synth_prepared, monkeypatch, model):
    meta = torch.device("meta")
    monkeypatch.setattr(baselines.train, "setup_process", lambda config: (meta, 0, 1))
    monkeypatch.setattr(baselines.models.lanegap, "match_layers", identity_matching)
    monkeypatch.setattr(baselines.models.piecewise, "match_layers", identity_matching)
    config = resolve_config("tiny", modality="camera", model=model)
    s = setup(config, PreparedData.open(synth_prepared["av2"]))
    held = [*s.trainer.model.parameters(), *s.trainer.model.buffers(), *s.trainer.criterion.buffers()]
    assert held and {t.device for t in held} == {meta}
    batch = next(iter(s.loader))
    mode = MixedDevices()
    with mode:
        losses = s.trainer.criterion(s.trainer.model(batch.to(meta).sensors), batch.to(meta).targets)
        losses["loss"].backward()
    assert mode.mixed == [], mode.mixed[:5]
    assert all(p.grad is None or p.grad.device == meta for p in s.trainer.model.parameters())
