"""How a run uses its device, the same in `cli train` and `cli eval` (so that eval's frame rates are
measured under the training's settings): CUDA's backend settings and the autocast precision."""

from __future__ import annotations

import torch


def cuda_settings(device: torch.device) -> None:
    """cuDNN's autotuner and TF32 for the fp32 matrix products and convolutions that autocast leaves in
    fp32; the geometry (camera projection, sampling grids, curves) is not a matrix product
    (pipeline/camera.py). Nothing on the CPU."""
    if device.type != "cuda":
        return
    torch.backends.cudnn.benchmark = True
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True


def amp_settings(device: torch.device, enabled: bool) -> tuple[torch.dtype | None, bool]:
    """(autocast dtype or None, whether a GradScaler is needed)."""
    if device.type != "cuda" or not enabled:
        return None, False
    if torch.cuda.is_bf16_supported():
        return torch.bfloat16, False
    return torch.float16, True
