"""Spatial representation alignment (Spatial Forcing, arXiv 2510.12276).

The backbone's hidden states at layer k, at the visual-token positions, are projected into a frozen
teacher's feature space and pulled toward the teacher's per-token features with a cosine loss.
Follows OpenHelix-Team/Spatial-Forcing (``vla-scripts/finetune_align.py``, ``AlignProjector``):
projector LayerNorm + Linear-GELU-Linear with Xavier-uniform weights and zero biases, loss
1 − mean cosine over tokens, weight 0.5. Deviation: student and teacher tokens are paired one to one;
the original's one-token shift (``gain_feat_1move``) is available as ``shift_one_token``.
Tokens the teacher has no target for (NaN features: missing depth) are left out of the mean, as a
depth-aware loss masks invalid pixels; a sample without any valid token is left out of the batch's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from capvector.backbones.base import OutputRequest, VLABackbone, VLAOutput
from capvector.data.batch import Batch
from capvector.errors import CapVectorError
from capvector.objectives.base import OBJECTIVES, Objective
from capvector.objectives.teachers import Teacher, build_teacher


class AlignProjector(nn.Module):
    def __init__(
        self, student_dim: int, teacher_dim: int, layernorm: bool, generator: torch.Generator
    ) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(student_dim) if layernorm else nn.Identity()
        self.fc1 = nn.Linear(student_dim, teacher_dim)
        self.fc2 = nn.Linear(teacher_dim, teacher_dim)
        for layer in (self.fc1, self.fc2):
            nn.init.xavier_uniform_(layer.weight, generator=generator)
            nn.init.zeros_(layer.bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(self.norm(x))))


@OBJECTIVES.register("spatial")
class SpatialAlignment(Objective):
    """Loss = 1 − mean cosine(projector(h_k at visual tokens), teacher features)."""

    def __init__(
        self,
        teacher: Teacher | str | None = None,
        layer: int | None = None,
        weight: float = 0.5,
        projector_layernorm: bool = True,
        shift_one_token: bool = False,
        name: str = "spatial_alignment",
        seed: int = 0,
    ) -> None:
        """
        Args:
            teacher: frozen target features, or a teacher's name (``geometric``, or
                ``module:Class``) to build with its defaults; default ``GeometricTeacher``
                (depth-based, no download).
            layer: hidden-state index of the student (default: the backbone's ``alignment_layer``,
                3/4 of the depth for OpenVLA-OFT, 24 of 32; 2/3 for Pi0.5, 12 of 18).
            weight: α in L = L_action + α·L_align (0.5 in Spatial Forcing).
            projector_layernorm: LayerNorm before the projector (Spatial Forcing's use_vlm_norm).
            shift_one_token: pair student token k+1 with teacher token k, as the original code.
            seed: the projector's initialisation seed; it draws from its own generator, so attaching
                the objective leaves the global random stream (and plain SFT) untouched.
        """
        super().__init__(name=name, weight=weight)
        # Kept out of the module tree: not trained, not checkpointed, not wrapped by DDP.
        object.__setattr__(self, "teacher", build_teacher(teacher))
        self.layer = layer
        self.projector_layernorm = projector_layernorm
        self.shift_one_token = shift_one_token
        self.seed = seed
        self.projector: AlignProjector | None = None

    def bind(self, backbone: VLABackbone) -> None:
        if self.layer is None:
            self.layer = backbone.alignment_layer
        if not 0 <= self.layer <= backbone.num_layers:
            raise CapVectorError(
                f"spatial alignment layer {self.layer} is outside 0..{backbone.num_layers} of {type(backbone).__name__}"
            )
        if self.projector is None:
            generator = torch.Generator().manual_seed(self.seed)
            # nn.Linear draws a default init from the global stream before ours replaces it: fork
            # the stream so attaching the objective changes nothing else in the run.
            with torch.random.fork_rng(devices=[]):
                self.projector = AlignProjector(
                    backbone.hidden_size,
                    self.teacher.feature_dim,
                    self.projector_layernorm,
                    generator,
                )

    @property
    def request(self) -> OutputRequest:
        return OutputRequest(hidden_layers=(self.layer,))

    def forward(self, batch: Batch, output: VLAOutput, backbone: VLABackbone) -> Tensor:
        hidden = output.hidden_states[self.layer]
        mask = output.visual_token_mask
        if self.shift_one_token:
            mask = torch.roll(mask, shifts=1, dims=1)
        batch_size = hidden.shape[0]
        student = hidden[mask].view(batch_size, -1, hidden.shape[-1])
        self.teacher.to(hidden.device)
        target = self.teacher(batch, output.visual_grid)
        if target.shape[1] != student.shape[1]:
            raise CapVectorError(
                f"teacher gave {target.shape[1]} tokens for {student.shape[1]} visual tokens "
                f"(grid {output.visual_grid}); its output must follow the student's token grid"
            )
        target = target.float()
        valid = target.isfinite().all(dim=-1)  # (B, tokens)
        projected = self.projector(student).float()
        if bool(valid.all()):  # the plain mean, as before masking existed
            cosine = F.cosine_similarity(projected, target, dim=-1)
            return (1 - cosine.mean(dim=1)).mean()
        cosine = F.cosine_similarity(projected, target.nan_to_num(0.0), dim=-1) * valid
        tokens = valid.sum(dim=1)
        samples = tokens > 0
        if not bool(samples.any()):  # no target at all: no pull, and a graph for backward
            return cosine.sum() * 0.0
        per_sample = cosine.sum(dim=1)[samples] / tokens[samples]
        return (1 - per_sample).mean()
