"""Camera projection: the sensor rig's geometry, shared by the encoder (BEV queries into the images),
the training data (intrinsics of resized images) and the figures (graphs drawn onto a camera image)."""

from __future__ import annotations

import numpy as np
import torch


def scaled_intrinsics(intrinsics: np.ndarray, scale_x: float, scale_y: float) -> np.ndarray:
    """Intrinsics of a resized image; pixel centres (OpenCV convention) map as (u + 0.5) * s - 0.5."""
    k = intrinsics.copy()
    k[0, 0], k[0, 1], k[0, 2] = k[0, 0] * scale_x, k[0, 1] * scale_x, (k[0, 2] + 0.5) * scale_x - 0.5
    k[1, 1], k[1, 2] = k[1, 1] * scale_y, (k[1, 2] + 0.5) * scale_y - 0.5
    return k


def project_points(
    points: torch.Tensor, intrinsics: torch.Tensor, sensor_to_ego: torch.Tensor, image_sizes: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Project BEV-frame points, (P, 3) shared by the batch or (B, P, 3), into every camera.

    Returns pixels (B, Ncam, P, 2) as (u, v) in the OpenCV convention (pixel (0, 0)'s centre at 0, 0)
    and visible (B, Ncam, P): in front of the camera and inside its image.
    """
    ego_to_camera = torch.linalg.inv(sensor_to_ego.float())[:, :, None, :3]  # (B, Ncam, 1, 3, 4)
    points = points.float().expand(sensor_to_ego.shape[0], -1, -1)[:, None]  # (B, 1, P, 3)
    intrinsics = intrinsics.float()[:, :, None]  # (B, Ncam, 1, 3, 3)
    # Sums of products in fp32, not einsum: a matrix product runs in bf16 under autocast, and in TF32 on
    # a GPU that allows it (pixels must be right to a fraction of a feature cell).
    in_camera = ego_to_camera[..., 3] + sum(ego_to_camera[..., j] * points[..., j, None] for j in range(3))
    depth = in_camera[..., 2]  # in_camera: (B, Ncam, P, 3)
    on_image = sum(intrinsics[..., j] * in_camera[..., j, None] for j in range(3))
    pixels = on_image[..., :2] / depth.clamp(min=1e-3).unsqueeze(-1)
    height = image_sizes[..., 0:1].float()
    width = image_sizes[..., 1:2].float()
    visible = (
        (depth > 0.1)
        & (pixels[..., 0] >= -0.5)
        & (pixels[..., 0] < width - 0.5)
        & (pixels[..., 1] >= -0.5)
        & (pixels[..., 1] < height - 0.5)
    )
    return pixels, visible
