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
    ego_to_camera = torch.linalg.inv(sensor_to_ego.float())
    points = points.expand(sensor_to_ego.shape[0], -1, -1)
    homogeneous = torch.cat([points, torch.ones_like(points[..., :1])], -1)  # (B, P, 4)
    in_camera = torch.einsum("bnij,bpj->bnpi", ego_to_camera[..., :3, :], homogeneous)
    depth = in_camera[..., 2]
    on_image = torch.einsum("bnij,bnpj->bnpi", intrinsics.float(), in_camera)
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
