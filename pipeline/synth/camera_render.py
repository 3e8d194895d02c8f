"""Camera images by ray casting: each pixel's ray meets the flat ground, which shows the ground texture.

The ground is flat and the ego level, so where each pixel's ray lands in the ego frame never changes:
it is computed once per camera, and a frame only moves those points into the world (an affine map)
before a cv2.remap into the texture. Far pixels cover more ground than a texel: like a real lens,
which averages over that footprint, they read a coarser level of the texture's mipmap pyramid, so that
thin lines fade with distance instead of flickering in and out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.synth.rig import CameraSpec
from pipeline.synth.texture import COLOURS_BGR, GRASS, MIP_LEVELS, RESOLUTION_M, GroundTexture

VIEW_RANGE_M = 60.0  # the ground fades into haze by this distance
HAZE_BGR = np.array([196, 190, 182], np.float32)
SKY_TOP_BGR, SKY_HORIZON_BGR = np.array([205, 150, 95], np.float32), np.array([230, 215, 200], np.float32)
JPEG_QUALITY = 75
OFF_MAP_BGR = [float(v) for v in COLOURS_BGR[GRASS]]  # beyond the texture: grass


@dataclass(frozen=True)
class CameraModel:
    spec: CameraSpec
    bands: list[tuple[int, slice, np.ndarray]]  # (mipmap level, image rows, their (rows, w, 2) ego x, y)
    ground_weight: (
        np.ndarray
    )  # (h, w, 3) uint8: 255 near (times the vignette), 0 by VIEW_RANGE_M and in the sky
    haze: np.ndarray  # (h, w, 3) uint8: the haze or sky that makes up the rest of each pixel


def camera_model(spec: CameraSpec) -> CameraModel:
    v, u = np.mgrid[0 : spec.height, 0 : spec.width].astype(np.float64) + 0.5
    rays = np.stack([(u - spec.cx) / spec.focal, (v - spec.cy) / spec.focal, np.ones_like(u)], axis=-1)
    rays = rays @ spec.rotation.T  # into the ego frame
    down = rays[..., 2] < -1e-9
    t = np.where(down, -spec.translation[2] / np.where(down, rays[..., 2], -1.0), 0.0)
    gx, gy = spec.translation[0] + t * rays[..., 0], spec.translation[1] + t * rays[..., 1]
    distance = np.hypot(gx - spec.translation[0], gy - spec.translation[1])
    ground = down & (distance < VIEW_RANGE_M)
    weight = np.where(ground, 1.0 - np.clip(distance / VIEW_RANGE_M, 0.0, 1.0) ** 1.5, 0.0)[..., None]
    elevation = np.arctan2(rays[..., 2], np.hypot(rays[..., 0], rays[..., 1]))
    sky = np.clip(elevation / 0.5, 0.0, 1.0)[..., None]
    background = np.where(down[..., None], HAZE_BGR, (1 - sky) * SKY_HORIZON_BGR + sky * SKY_TOP_BGR)
    r2 = ((u - spec.width / 2) ** 2 + (v - spec.height / 2) ** 2) / spec.width**2
    vignette = (1.0 - 0.35 * r2)[..., None]
    # ground seen by one pixel of a row (the camera is level: rows are lines of equal depth t): about
    # t / focal across the ray and t^2 / (focal * height) along it; the level matches their geometric mean
    depth = t[:, spec.width // 2]
    footprint = np.sqrt(np.maximum(depth, 1e-9) ** 3 / (spec.focal**2 * spec.translation[2]))
    level = np.clip(np.round(np.log2(footprint / RESOLUTION_M)), 0, MIP_LEVELS - 1).astype(int)
    xy = np.stack([gx, gy], axis=-1).astype(np.float32)
    rows = np.flatnonzero(ground.any(axis=1))
    bands = []
    for k in np.unique(level[rows]):
        band = rows[level[rows] == k]
        bands.append((int(k), slice(band[0], band[-1] + 1), xy[band[0] : band[-1] + 1]))
    return CameraModel(
        spec,
        bands,
        np.repeat(np.round(255 * weight * vignette), 3, axis=2).astype(np.uint8),
        np.round(background * (1 - weight) * vignette).astype(np.uint8),
    )


@dataclass(frozen=True)
class Lighting:
    """One log's light and camera response: the day's sun or overcast, the white balance, the sensor."""

    brightness: float  # gain on every channel
    contrast: float  # about mid-grey
    colour_gains: np.ndarray  # (3,) B, G, R: the colour temperature
    noise_sigma: float  # grey levels, per pixel and channel

    def transform(self, exposure: float) -> np.ndarray:
        """(3, 4) cv2.transform matrix: contrast about mid-grey, then the gains of the light and exposure."""
        gains = self.brightness * exposure * self.colour_gains
        return np.column_stack([np.diag(gains * self.contrast), gains * 128.0 * (1.0 - self.contrast)])


def draw_lighting(rng: np.random.Generator) -> Lighting:
    warmth = rng.uniform(-1.0, 1.0)  # -1: bluish overcast or shade, +1: warm low sun
    colour_gains = 1.0 + 0.08 * warmth * np.array([-1.0, 0.0, 1.0])
    return Lighting(rng.uniform(0.75, 1.2), rng.uniform(0.8, 1.2), colour_gains, rng.uniform(2.0, 5.0))


class Noise:
    """Sensor noise images cut from one bank of random bytes (centred on 128): cheap per image."""

    def __init__(self, rng: np.random.Generator, sigma: float, rows: int = 1024, width: int = 400):
        self.bank = np.clip(np.rint(rng.normal(128.0, sigma, (rows, width, 3))), 0, 255).astype(np.uint8)
        self.rng = rng

    def like(self, h: int, w: int) -> np.ndarray:
        row = self.rng.integers(0, self.bank.shape[0] - h)
        col = self.rng.integers(0, self.bank.shape[1] - w + 1)
        return self.bank[row : row + h, col : col + w]


def render(model: CameraModel, texture: GroundTexture, pose: np.ndarray, lighting: Lighting,
           noise: Noise) -> np.ndarray:  # fmt: skip
    """(h, w, 3) uint8 BGR image of the camera on the ego at pose (x, y, heading)."""
    spec = model.spec
    ground = np.zeros((spec.height, spec.width, 3), np.uint8)
    for level, rows, xy in model.bands:
        texels = cv2.transform(xy, texture.from_ego(pose, level))
        ground[rows] = cv2.remap(texture.pyramid[level], texels, None, cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=OFF_MAP_BGR)  # fmt: skip
    image = cv2.add(cv2.multiply(ground, model.ground_weight, scale=1.0 / 255.0), model.haze)
    exposure = noise.rng.uniform(0.9, 1.1)  # auto exposure varies a little from image to image
    image = cv2.transform(image, lighting.transform(exposure))
    return cv2.addWeighted(image, 1.0, noise.like(*image.shape[:2]), 1.0, -128.0)


def encode_jpeg(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return data.tobytes()
