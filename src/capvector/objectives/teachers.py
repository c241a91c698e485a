"""Frozen teachers for spatial alignment: per-visual-token target features.

A teacher maps a batch to targets ``(B, N_cam * rows * cols, D)`` on the student's token grid, in
the backbone's token order (camera by camera, patches row-major). A token the teacher has no target
for (its depth all missing) is NaN in every feature; the loss leaves such tokens out. Teachers never train: they have
no trainable parameters, run under ``no_grad`` and live outside the module tree (see
``SpatialAlignment``), so they are not in the optimizer, the checkpoint or a DDP wrapper.

- ``GeometricTeacher`` (default): 3-D structure from the demos' depth maps, no download.
- ``TimmTeacher``: any timm vision model from a local weights file (e.g. DINOv2, SigLIP).
- ``ExternalTeacher``: any user module by import path (e.g. VGGT, Spatial Forcing's teacher).

They are registered in ``TEACHERS`` as ``geometric``, ``timm`` and ``external``; a teacher of your
own is named ``module:Class``.
"""

from __future__ import annotations

import inspect
import math
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from capvector.data.batch import Batch
from capvector.errors import CapVectorError
from capvector.io.loading import load_safetensors, load_torch
from capvector.registry import Registry, import_object


class Teacher(nn.Module, ABC):
    feature_dim: int

    @abstractmethod
    def forward(self, batch: Batch, grid: tuple[int, int]) -> Tensor:
        """Targets (B, N_cam * rows * cols, feature_dim) for a ``grid`` of (rows, cols) per camera."""


TEACHERS: Registry[type[Teacher]] = Registry("teacher", base=Teacher, error=CapVectorError)


def build_teacher(teacher: Teacher | str | None) -> Teacher:
    """``teacher`` itself, or the teacher a name or ``module:Class`` names, with its defaults;
    None: the geometric teacher (no download)."""
    if isinstance(teacher, Teacher):
        return teacher
    cls = TEACHERS.get(teacher or "geometric")
    required = [
        p.name
        for p in inspect.signature(cls).parameters.values()
        if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    if required:
        raise CapVectorError(
            f"teacher {teacher!r} needs {', '.join(required)}: give it as a class_path with "
            "init_args instead of by name"
        )
    return cls()


def sine_position_embedding(rows: int, cols: int, dim: int, omega0: float = 100.0) -> Tensor:
    """(rows * cols, dim) 2-D sinusoidal embedding, half the channels for x and half for y.

    Spatial Forcing's ``use_vggt_pe``: a normalised UV grid (aspect aware, spans divided by the
    diagonal), frequencies from ``omega0``; the caller scales it by 0.1 before adding.
    """
    diag = math.hypot(rows, cols)
    v = (torch.arange(rows, dtype=torch.float32) - (rows - 1) / 2) / diag
    u = (torch.arange(cols, dtype=torch.float32) - (cols - 1) / 2) / diag
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    quarter = dim // 4
    # Angular frequencies from 1 to omega0 over a unit span, geometrically spaced.
    freqs = omega0 ** (torch.arange(quarter, dtype=torch.float32) / max(1, quarter - 1))
    parts = []
    for coord in (uu.reshape(-1), vv.reshape(-1)):
        angles = coord[:, None] * freqs[None]
        parts += [angles.sin(), angles.cos()]
    embedding = torch.cat(parts, dim=-1)
    return F.pad(embedding, (0, dim - embedding.shape[-1]))


@TEACHERS.register("geometric")
class GeometricTeacher(Teacher):
    """Per-patch 3-D structure from depth and camera intrinsics, lifted to fixed features.

    Every pixel is back-projected to a camera-frame point (X, Y, Z) and gets a surface normal from
    the cross product of neighbouring points. Per token, the mean and spread of these 6 values
    (12 numbers) are lifted by fixed random Fourier features to ``feature_dim`` (a seeded buffer,
    never trained), so cosine similarity in target space reflects geometric similarity. This is
    our stand-in for VGGT's geometry features (Spatial Forcing), computable from what the demos
    carry, with no download.

    Depth of NaN, inf or <= 0 is missing, as real depth sensors report a pixel they could not
    measure (NaN, or 0 in the ROS/RealSense convention): it and the normals that would difference
    across it are left out of each token's mean and spread, and a token with no valid point gets
    NaN features (no target). With every pixel valid the features are those of the plain means.
    """

    def __init__(
        self,
        feature_dim: int = 64,
        position_embedding: bool = True,
        scale: float = 2.0,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if feature_dim % 2:
            raise CapVectorError(f"GeometricTeacher.feature_dim must be even, got {feature_dim}")
        self.feature_dim = feature_dim
        self.position_embedding = position_embedding
        generator = torch.Generator().manual_seed(seed)
        self.register_buffer(
            "frequencies", torch.randn(12, feature_dim // 2, generator=generator) * scale
        )

    @torch.no_grad()
    def forward(self, batch: Batch, grid: tuple[int, int]) -> Tensor:
        if "depth" not in batch or "intrinsics" not in batch:
            raise CapVectorError(
                "the geometric teacher needs depth maps and camera intrinsics: set data.load_depth=true "
                "and record demos with depth (`capvector demos --depth`)"
            )
        depth: Tensor = batch["depth"].float()  # (B, N, H, W)
        intrinsics: Tensor = batch["intrinsics"].float()  # (B, N, 3, 3)
        b, n, h, w = depth.shape
        valid = torch.isfinite(depth) & (depth > 0)
        depth = torch.where(valid, depth, torch.ones_like(depth))  # placeholders, weighted out
        v, u = torch.meshgrid(
            torch.arange(h, device=depth.device, dtype=depth.dtype) + 0.5,
            torch.arange(w, device=depth.device, dtype=depth.dtype) + 0.5,
            indexing="ij",
        )
        fx, fy = intrinsics[..., 0, 0, None, None], intrinsics[..., 1, 1, None, None]
        cx, cy = intrinsics[..., 0, 2, None, None], intrinsics[..., 1, 2, None, None]
        points = torch.stack(
            [(u - cx) * depth / fx, (v - cy) * depth / fy, depth], dim=2
        )  # (B,N,3,H,W)
        du = torch.diff(points, dim=-1)
        dv = torch.diff(points, dim=-2)
        du = torch.cat([du, du[..., -1:]], dim=-1)  # repeat the border difference
        dv = torch.cat([dv, dv[..., -1:, :]], dim=-2)
        # A normal is valid where the pixel and the neighbours it differences with are.
        valid_u = valid[..., 1:] & valid[..., :-1]
        valid_v = valid[..., 1:, :] & valid[..., :-1, :]
        normal_valid = (
            torch.cat([valid_u, valid_u[..., -1:]], dim=-1)
            & torch.cat([valid_v, valid_v[..., -1:, :]], dim=-2)
        ).flatten(0, 1)[:, None]  # (B*N, 1, H, W)
        # Neighbours' cross product turns with the pixel grid's handedness: images mirrored
        # against their camera (LIBERO's, read rotated 180 degrees from bottom-up frames: fx < 0)
        # would get the opposite normals of the same surface. sign(fx * fy) keeps one convention.
        normals = F.normalize(torch.cross(du, dv, dim=2), dim=2) * torch.sign(fx * fy).unsqueeze(2)
        point_valid = valid.flatten(0, 1)[:, None]  # (B*N, 1, H, W)
        mean_p, spread_p, count = _masked_pool(points.flatten(0, 1), point_valid, grid)
        mean_n, spread_n, _ = _masked_pool(normals.flatten(0, 1), normal_valid, grid)
        mean = torch.cat([mean_p, mean_n], dim=1)
        spread = torch.cat([spread_p, spread_n], dim=1)
        descriptor = (
            torch.cat([mean, spread], dim=1).flatten(2).transpose(1, 2)
        )  # (B*N, tokens, 12)
        projected = descriptor @ self.frequencies
        features = torch.cat([projected.sin(), projected.cos()], dim=-1)
        if self.position_embedding:
            pe = sine_position_embedding(*grid, self.feature_dim).to(features)
            features = features + 0.1 * pe  # Spatial Forcing adds its PE scaled by 0.1
        missing = (count == 0).flatten(1)[..., None]  # (B*N, tokens, 1): no valid point
        features = features.masked_fill(missing, float("nan"))
        return features.reshape(b, n * grid[0] * grid[1], self.feature_dim)


def _masked_pool(values: Tensor, weight: Tensor, grid: tuple[int, int]) -> tuple[Tensor, ...]:
    """Per-cell mean and spread of ``values`` (M, C, H, W) over the pixels where ``weight``
    (M, 1, H, W, bool) holds, and the share of such pixels (0: none). Averages of the weighted
    values over the average weight: with every weight 1 these are the plain averages, exactly."""
    weight = weight.to(values.dtype)
    share = F.adaptive_avg_pool2d(weight, grid)
    values = values * weight  # masked pixels hold placeholders (finite): zeroed here
    denominator = share.clamp_min(torch.finfo(values.dtype).tiny)
    mean = F.adaptive_avg_pool2d(values, grid) / denominator
    square = F.adaptive_avg_pool2d(values * values, grid) / denominator
    return mean, (square - mean**2).clamp_min(0).sqrt(), share


def _pool_feature_map(features: Tensor, grid: tuple[int, int], batch: int) -> Tensor:
    """(B*N, D, h, w) -> (B, N*rows*cols, D), bilinear with aligned corners as Spatial Forcing."""
    pooled = F.interpolate(features.float(), size=grid, mode="bilinear", align_corners=True)
    return pooled.flatten(2).transpose(1, 2).reshape(batch, -1, features.shape[1])


@TEACHERS.register("timm")
class TimmTeacher(Teacher):
    """A timm ViT (any ``forward_intermediates`` model) loaded from a local weights file."""

    def __init__(
        self,
        model_name: str,
        weights: str,
        layer: int = -1,
        image_size: int | None = None,
        model_kwargs: dict[str, Any] | None = None,
    ) -> None:
        import timm

        super().__init__()
        extra = dict(model_kwargs or {})
        if image_size is not None:
            extra["img_size"] = image_size
        self.model = timm.create_model(model_name, pretrained=False, num_classes=0, **extra)
        _load_weights(self.model, weights)
        self.model.eval().requires_grad_(False)
        self.layer = layer
        self.feature_dim = self.model.num_features
        config = self.model.pretrained_cfg or {}
        self.register_buffer(
            "mean", torch.tensor(config.get("mean", (0.5,) * 3)).view(1, 3, 1, 1), persistent=False
        )
        self.register_buffer(
            "std", torch.tensor(config.get("std", (0.5,) * 3)).view(1, 3, 1, 1), persistent=False
        )
        self.input_size = self.model.patch_embed.img_size

    @torch.no_grad()
    def forward(self, batch: Batch, grid: tuple[int, int]) -> Tensor:
        images: Tensor = batch["images"]
        flat = images.flatten(0, 1).float()
        if tuple(flat.shape[-2:]) != tuple(self.input_size):
            flat = F.interpolate(
                flat, size=self.input_size, mode="bicubic", align_corners=False
            ).clamp(0, 1)
        index = self.layer % len(self.model.blocks)
        (features,) = self.model.forward_intermediates(
            (flat - self.mean) / self.std,
            indices=[index],
            output_fmt="NCHW",
            intermediates_only=True,
        )
        return _pool_feature_map(features, grid, images.shape[0])


@TEACHERS.register("external")
class ExternalTeacher(Teacher):
    """A user module by import path (``module:Class``, or ``module.Class``), e.g. a VGGT
    aggregator where the user has it.

    The module is called on images (B*N, 3, H, W) in [0, 1] and must return a feature map
    (B*N, D, h, w); ``feature_dim`` is D. Weights load from a local file when given.
    """

    def __init__(
        self,
        class_path: str,
        feature_dim: int,
        init_args: dict[str, Any] | None = None,
        weights: str | None = None,
    ) -> None:
        super().__init__()
        self.model = import_object(class_path, "teacher class")(**(init_args or {}))
        if weights:
            _load_weights(self.model, weights)
        self.model.eval().requires_grad_(False)
        self.feature_dim = feature_dim

    @torch.no_grad()
    def forward(self, batch: Batch, grid: tuple[int, int]) -> Tensor:
        images: Tensor = batch["images"]
        features = self.model(images.flatten(0, 1).float())
        if features.ndim != 4 or features.shape[1] != self.feature_dim:
            raise CapVectorError(
                f"teacher returned shape {tuple(features.shape)}; expected (B*N, {self.feature_dim}, h, w)"
            )
        return _pool_feature_map(features, grid, images.shape[0])


def _load_weights(model: nn.Module, path: str) -> None:
    if not Path(path).is_file():
        raise CapVectorError(
            f"teacher weights {path} do not exist (teachers load from local files only)"
        )
    if path.endswith(".safetensors"):
        state = load_safetensors(path)
    else:
        state = load_torch(path, weights_only=True)
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise CapVectorError(
            f"teacher weights {path} do not fit {type(model).__name__}: "
            f"missing {missing[:3]}{' ...' if len(missing) > 3 else ''}, "
            f"unexpected {unexpected[:3]}{' ...' if len(unexpected) > 3 else ''}"
        )
