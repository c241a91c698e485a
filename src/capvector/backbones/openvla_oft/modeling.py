"""OpenVLA-OFT-style backbone: fused DINOv2 + SigLIP vision, Llama with bidirectional attention,
parallel decoding of an action chunk and an MLP-ResNet L1 head; optionally OFT+'s FiLM language
conditioning of the vision backbone (the ALOHA recipe).

Faithful to moojink/openvla-oft (``prismatic/extern/hf/modeling_prismatic.py``,
``prismatic/models/action_heads.py``, ``prismatic/models/projectors.py``,
``prismatic/models/film_vit_wrapper.py``, ``vla-scripts/finetune.py``) and its transformers fork
(bidirectional SDPA attention); ``tests/backbones/openvla_oft/test_parity_openvla_oft.py`` checks it
against outputs of that code. The config and presets are in ``configuration.py``; reading
upstream's checkpoint folders is in ``convert.py``.

Sequence layout (one row, right padded):
``[BOS] [N_cam x patches visual tokens] [proprio token] [prompt] [T*A action slots] [</s>] [pad]``
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from capvector.backbones.base import (
    IGNORE_INDEX,
    BackboneError,
    ImportOption,
    OutputRequest,
    VLABackbone,
    VLAOutput,
    keep_hidden_states,
    project_onto_vocabulary,
    register_family,
)
from capvector.backbones.common import (
    MLPResNet,
    answer_ids_then_eos,
    check_cameras,
    right_pad,
)
from capvector.backbones.materialize import float32_until_attached
from capvector.backbones.openvla_oft.configuration import LlamaSpec, OpenVLAOFTConfig, ViTConfig
from capvector.data.batch import Batch

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SIGLIP_MEAN = (0.5, 0.5, 0.5)
SIGLIP_STD = (0.5, 0.5, 0.5)


def _build_vit(spec: ViTConfig, image_size: int, film: bool = False) -> nn.Module:
    from timm.models.vision_transformer import Block, VisionTransformer

    # timm re-draws every weight at the end of the constructor (``init_weights``), with its own
    # truncated normal: built in float32, cast when attached (a frozen-dtype build).
    with float32_until_attached():
        return VisionTransformer(
            img_size=image_size,
            patch_size=spec.patch_size,
            num_classes=0,
            global_pool=spec.global_pool,
            embed_dim=spec.embed_dim,
            depth=spec.depth,
            num_heads=spec.num_heads,
            mlp_ratio=spec.mlp_ratio,
            init_values=spec.layer_scale_init,
            class_token=spec.class_token,
            no_embed_class=spec.no_embed_class,
            reg_tokens=spec.reg_tokens,
            act_layer=spec.act_layer,
            block_fn=_filmed_block_class() if film else Block,
        )


class FiLM(nn.Module):
    """Per-block FiLM projections of OFT+ (``FiLMedVisionTransformerBlock`` in
    ``prismatic/models/film_vit_wrapper.py``): gamma and beta from the mean language embedding."""

    def __init__(self, llm_dim: int, vision_dim: int) -> None:
        super().__init__()
        self.scale = nn.Linear(llm_dim, vision_dim)
        self.shift = nn.Linear(llm_dim, vision_dim)


@functools.cache
def _filmed_block_class() -> type[nn.Module]:
    """timm's ``Block`` that applies FiLM between its residuals when given one (built lazily: timm
    is imported on first use)."""
    from timm.models.vision_transformer import Block

    class FiLMedBlock(Block):
        """``FiLMedVisionTransformerBlock`` of ``prismatic/models/film_vit_wrapper.py``:
        ``x * (1 + gamma) + beta`` after the attention residual, so zero projections change nothing.
        A subclass, not a wrapper, so parameter names stay timm's and FSDP2 units / activation
        checkpointing (hooks on the block) see the call."""

        def forward(
            self,
            x: Tensor,
            attn_mask: Tensor | None = None,
            is_causal: bool = False,
            film: FiLM | None = None,
            language: Tensor | None = None,
        ) -> Tensor:
            if film is None:
                return super().forward(x, attn_mask=attn_mask, is_causal=is_causal)
            attn = self.attn(self.norm1(x), attn_mask=attn_mask, is_causal=is_causal)
            x = x + self.drop_path1(self.ls1(attn))
            x = x * (1 + film.scale(language).unsqueeze(1)) + film.shift(language).unsqueeze(1)
            return x + self.drop_path2(self.ls2(self.mlp(self.norm2(x))))

    return FiLMedBlock


class FusedVisionBackbone(nn.Module):
    """DINOv2 + SigLIP patch features of the second-to-last block, concatenated per patch.

    As Prismatic's ``PrismaticVisionBackbone``: prefix tokens dropped, no final norm, each image
    normalised twice (ImageNet statistics for DINOv2, 0.5/0.5 for SigLIP). With ``film`` each block
    of both ViTs is FiLM-conditioned on the language (OFT+).
    """

    def __init__(self, config: OpenVLAOFTConfig) -> None:
        super().__init__()
        self.featurizer = _build_vit(config.featurizer, config.image_size, config.film)
        self.fused_featurizer = _build_vit(config.fused_featurizer, config.image_size, config.film)
        self.featurizer_film: nn.ModuleList | None = None
        self.fused_featurizer_film: nn.ModuleList | None = None
        if config.film:
            llm_dim = config.llm.hidden_size
            self.featurizer_film = nn.ModuleList(
                FiLM(llm_dim, config.featurizer.embed_dim) for _ in self.featurizer.blocks
            )
            self.fused_featurizer_film = nn.ModuleList(
                FiLM(llm_dim, config.fused_featurizer.embed_dim)
                for _ in self.fused_featurizer.blocks
            )
        self.register_buffer(
            "dino_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False
        )
        self.register_buffer(
            "dino_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False
        )
        self.register_buffer(
            "siglip_mean", torch.tensor(SIGLIP_MEAN).view(1, 3, 1, 1), persistent=False
        )
        self.register_buffer(
            "siglip_std", torch.tensor(SIGLIP_STD).view(1, 3, 1, 1), persistent=False
        )
        self.grid = config.image_size // config.featurizer.patch_size

    @property
    def embed_dim(self) -> int:
        return self.featurizer.embed_dim + self.fused_featurizer.embed_dim

    def forward(self, images: Tensor, language: Tensor | None = None) -> Tensor:
        """(B', 3, H, W) in [0, 1] -> (B', patches, D_dino + D_siglip).

        ``language`` (B', H_llm): the mean language embedding of each image's sample, required
        with FiLM and ignored without.
        """
        features = []
        for vit, films, mean, std in (
            (self.featurizer, self.featurizer_film, self.dino_mean, self.dino_std),
            (self.fused_featurizer, self.fused_featurizer_film, self.siglip_mean, self.siglip_std),
        ):
            x = (images - mean) / std
            if films is None:
                (out,) = vit.forward_intermediates(
                    x,
                    indices=[len(vit.blocks) - 2],
                    norm=False,
                    stop_early=True,
                    output_fmt="NLC",
                    intermediates_only=True,
                )
            else:
                if language is None:
                    raise BackboneError("a FiLM vision backbone needs the language embedding")
                # FiLMedVisionTransformer._intermediate_layers: the same stem, then FiLM blocks up
                # to the second-to-last one.
                x = vit.norm_pre(vit.patch_drop(vit._pos_embed(vit.patch_embed(x))))
                for block, film in zip(vit.blocks[:-1], films, strict=False):
                    x = block(x, film=film, language=language)
                out = x[:, vit.num_prefix_tokens :]
            features.append(out)
        return torch.cat(features, dim=-1)


class EfficientNetVision(nn.Module):
    """timm's ``tf_efficientnet_lite0`` trunk (no pooling, no classifier): the ``*-mini`` vision
    tower. (B', 3, H, W) in [0, 1] -> (B', H/32 * W/32, 1280), row-major patches.

    Its BatchNorm layers always normalise with their ImageNet running statistics: the tower is
    frozen, and batch statistics of 8 robot images would move what every later layer was
    pretrained on (detectron2's FrozenBatchNorm2d makes the same choice).
    """

    embed_dim = 1280

    def __init__(self, config: OpenVLAOFTConfig) -> None:
        super().__init__()
        import timm

        if config.image_size % 32:
            raise BackboneError(f"image_size {config.image_size} is not a multiple of 32")
        self.model = timm.create_model("tf_efficientnet_lite0", pretrained=False, num_classes=0)
        self.model.eval()  # frozen running statistics, see the class docstring
        self.model.keeps_eval_mode = True  # expected at fit start (VLAModule.on_fit_start)
        self.grid = config.image_size // 32

    def train(self, mode: bool = True) -> EfficientNetVision:
        super().train(mode)
        self.model.eval()  # frozen running statistics, see the class docstring
        return self

    def forward(self, images: Tensor, language: Tensor | None = None) -> Tensor:
        # A bf16 frozen base (model.frozen_dtype) casts parameters only; BatchNorm needs its running
        # statistics in the weights' dtype too.
        dtype = self.model.conv_stem.weight.dtype
        if self.model.bn1.running_mean.dtype != dtype:
            self.model.to(dtype)
        # timm's pretrained_cfg for tf_efficientnet_lite0: mean = std = 0.5, i.e. inputs in [-1, 1].
        features = self.model.forward_features(images * 2 - 1)
        return features.flatten(2).transpose(1, 2)


class MLPProjector(nn.Module):
    """A two-layer GELU MLP D -> hidden -> LLM width (Prismatic's ``gelu-mlp`` with a bottleneck)."""

    def __init__(self, vision_dim: int, hidden: int, llm_dim: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(vision_dim, hidden)
        self.fc2 = nn.Linear(hidden, llm_dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class FusedProjector(nn.Module):
    """Prismatic's ``no-align+fused-gelu-mlp``: D -> 4D -> LLM width -> LLM width."""

    def __init__(self, vision_dim: int, llm_dim: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(vision_dim, 4 * vision_dim)
        self.fc2 = nn.Linear(4 * vision_dim, llm_dim)
        self.fc3 = nn.Linear(llm_dim, llm_dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc3(F.gelu(self.fc2(F.gelu(self.fc1(x)))))


class ProprioProjector(nn.Module):
    """One LLM token from the proprio state (``prismatic/models/projectors.py``)."""

    def __init__(self, proprio_dim: int, llm_dim: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(proprio_dim, llm_dim)
        self.fc2 = nn.Linear(llm_dim, llm_dim)

    def forward(self, proprio: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(proprio)))


class L1RegressionActionHead(nn.Module):
    """The A hidden states of one timestep, concatenated, -> MLP-ResNet -> A action values."""

    def __init__(
        self, llm_dim: int, action_dim: int, num_blocks: int, hidden: int | None = None
    ) -> None:
        super().__init__()
        self.action_dim = action_dim
        self.model = MLPResNet(num_blocks, action_dim * llm_dim, hidden or llm_dim, action_dim)

    def forward(self, hidden: Tensor) -> Tensor:
        """(B, T*A, H) -> (B, T, A)."""
        batch, slots, width = hidden.shape
        return self.model(hidden.reshape(batch, slots // self.action_dim, self.action_dim * width))


@register_family
class OpenVLAOFT(VLABackbone):
    config_class = OpenVLAOFTConfig
    original_loader = "capvector.backbones.openvla_oft.convert"
    import_options = (
        ImportOption(
            "apply_lora_adapter",
            "merge the run's lora_adapter/ into the weights (released folders hold merged ones)",
            type=bool,
        ),
    )

    # peft full-match regex: OFT uses "all-linear" (every Linear of the LLM, both ViTs and the
    # projector). We leave out SigLIP's attention-pool head: its output is never used, so its LoRA
    # would get no gradient (the reason OFT needs DDP's find_unused_parameters=True).
    @property
    def lora_target_modules(self) -> str:  # type: ignore[override]
        llm = (
            r"language_model\.model\.layers\.\d+\.(self_attn\.[qkvo]_proj|mlp\.(gate|up|down)_proj)"
        )
        if self.config.vision != "fused-vit":
            # The mini: LoRA on the language model only; the pretrained CNN stays frozen and the
            # projector, new, trains in full (lora_trainable_modules).
            return llm

        # The last block of each ViT never runs (features come from the one before), so it gets
        # no LoRA either.
        def blocks(spec: ViTConfig) -> str:
            return "|".join(str(i) for i in range(spec.depth - 1))

        return (
            rf"({llm}"
            rf"|vision_backbone\.featurizer\.blocks\.({blocks(self.config.featurizer)})\.(attn\.(qkv|proj)|mlp\.fc[12])"
            rf"|vision_backbone\.fused_featurizer\.blocks\.({blocks(self.config.fused_featurizer)})\.(attn\.(qkv|proj)|mlp\.fc[12])"
            r"|projector\.fc[123])"
        )

    # FiLM projections are new modules trained in full, as finetune.py adds them after LoRA.
    @property
    def lora_trainable_modules(self) -> tuple[str, ...]:  # type: ignore[override]
        heads = ("action_head.*", "proprio_projector.*", "vision_backbone.*_film.*")
        return heads if self.config.vision == "fused-vit" else (*heads[:2], "projector.*")

    # FiLM (OFT+) falls under vision_backbone.*: it is part of the vision pathway a vector moves,
    # and narrowing the globs would make new exports disagree with existing ones.
    capability_parameters = ("vision_backbone.*", "projector.*", "language_model.*")

    def __init__(self, config: OpenVLAOFTConfig) -> None:
        super().__init__(config)
        self.config: OpenVLAOFTConfig = config
        if config.vision not in ("fused-vit", "efficientnet-lite0"):
            raise BackboneError(
                f"vision {config.vision!r} is not one of 'fused-vit', 'efficientnet-lite0'"
            )
        if config.vision == "fused-vit" and config.image_size % config.featurizer.patch_size:
            raise BackboneError(
                f"image_size {config.image_size} is not a multiple of patch size "
                f"{config.featurizer.patch_size}"
            )
        if config.base_weights not in ("", "packages"):
            raise BackboneError(f"base_weights {config.base_weights!r} is not '' or 'packages'")
        # On the meta device (counting parameters) no weights are read, nor the packaged tokenizer
        # (it lives in the dequantised cache); the others load, as the planner's traced step
        # tokenizes its prompt.
        real = torch.empty(()).device.type != "meta"
        packaged = config.tokenizer == PACKAGED_TOKENIZER
        self._tokenizer = (
            _make_tokenizer(config.tokenizer)
            if config.tokenizer and (real or not packaged)
            else None
        )
        if config.vision == "fused-vit":
            self.vision_backbone: nn.Module = FusedVisionBackbone(config)
        else:
            self.vision_backbone = EfficientNetVision(config)
        llm = config.llm
        vision_dim = self.vision_backbone.embed_dim
        self.projector: nn.Module = (
            MLPProjector(vision_dim, config.projector_hidden, llm.hidden_size)
            if config.projector_hidden
            else FusedProjector(vision_dim, llm.hidden_size)
        )
        # The packaged base overwrites every weight of the language model: drawing 168 M random
        # embedding values first costs seconds for nothing (transformers' own no_init_weights, as
        # its from_pretrained does).
        self.language_model = _build_language_model(llm, init=config.base_weights != "packages")
        self.proprio_projector = (
            ProprioProjector(config.proprio_dim, llm.hidden_size) if config.proprio_dim else None
        )
        self.action_head = L1RegressionActionHead(
            llm.hidden_size, config.action_dim, config.head_blocks, config.head_hidden or None
        )
        if config.base_weights == "packages":
            from capvector.backbones.openvla_oft.packaged_base import attach_packaged_base

            attach_packaged_base(self, load=real)

    # -- contract ----------------------------------------------------------------------------

    @property
    def num_layers(self) -> int:
        return self.config.llm.num_layers

    @property
    def hidden_size(self) -> int:
        return self.config.llm.hidden_size

    def make_tokenizer(self, folder: str) -> Any:
        return _make_tokenizer(folder)

    def weight_provenance(self) -> list[dict[str, Any]]:
        if self.config.base_weights != "packages":
            return []
        from capvector.backbones.openvla_oft.packaged_base import provenance

        return provenance()

    @property
    def saves_tokenizer(self) -> bool:
        return self.config.tokenizer != PACKAGED_TOKENIZER

    @property
    def base_delta(self) -> dict[str, tuple[Tensor, Tensor]] | None:
        return getattr(self, "packaged_delta", None)

    def set_base_delta(self, deltas: Mapping[str, tuple[Tensor, Tensor]]) -> None:
        if self.config.base_weights != "packages":
            super().set_base_delta(deltas)
            return
        from capvector.backbones.openvla_oft.packaged_base import set_base_delta

        set_base_delta(self, deltas)

    def unused_parameter_names(self) -> list[str]:
        # Features come from the second-to-last ViT block without the final norm, and SigLIP's
        # attention-pool head is never called: these exist only so released checkpoints load.
        unused: list[str] = []
        if self.config.vision != "fused-vit":
            return unused
        for name in ("featurizer", "fused_featurizer"):
            vit = getattr(self.vision_backbone, name)
            last = len(vit.blocks) - 1
            prefix = f"vision_backbone.{name}."
            for param_name, _ in vit.named_parameters():
                if param_name.startswith(
                    (f"blocks.{last}.", "norm.", "attn_pool.", "fc_norm.", "head.")
                ):
                    unused.append(prefix + param_name)
            films = getattr(self.vision_backbone, f"{name}_film")
            if films is not None:
                unused += [
                    f"vision_backbone.{name}_film.{last}.{n}"
                    for n, _ in films[last].named_parameters()
                ]
        return unused

    def language_head_parameter_names(self) -> list[str]:
        if self.config.llm.architecture == "gemma3":
            return []  # Gemma's head is the tied token embedding, frozen with the packaged base
        return [
            f"language_model.lm_head.{n}" for n, _ in self.language_model.lm_head.named_parameters()
        ]

    def shard_units(self) -> list[nn.Module]:
        vision = self.vision_backbone
        if isinstance(vision, EfficientNetVision):
            return [*vision.model.blocks, *self.language_model.model.layers]
        return [
            *vision.featurizer.blocks,
            *vision.fused_featurizer.blocks,
            *self.language_model.model.layers,
        ]

    @property
    def num_visual_tokens(self) -> int:
        return self.config.num_images * self.vision_backbone.grid**2

    def forward(self, batch: Batch, request: OutputRequest | None = None) -> VLAOutput:
        request = request or OutputRequest()
        images: Tensor = batch["images"]
        device = images.device
        embeds, valid, slot_pos, n_prefix = self._embed_inputs(batch)
        hidden: dict[int, Tensor] = {}
        if 0 in request.hidden_layers:
            hidden[0] = embeds
        # Bidirectional attention as the OFT transformers fork: every token sees every non-pad
        # token (key-padding mask only), passed as an additive 4-D mask so SDPA is non-causal.
        mask = torch.zeros(
            valid.shape[0], 1, valid.shape[1], valid.shape[1], dtype=embeds.dtype, device=device
        )
        mask.masked_fill_(~valid[:, None, None, :], torch.finfo(embeds.dtype).min)
        positions = torch.arange(valid.shape[1], device=device).expand(valid.shape[0], -1)
        decoder = self.language_model.model
        with keep_hidden_states(decoder.layers, request.hidden_layers, hidden):
            last = decoder(
                inputs_embeds=embeds,
                attention_mask=self._layer_masks(mask),
                position_ids=positions,
                use_cache=False,
            ).last_hidden_state
        # Readout one position before each action slot: the next-token shift OFT keeps even with
        # bidirectional attention (finetune.py slices hidden states with labels[:, 1:]).
        readout = torch.gather(last, 1, (slot_pos - 1).unsqueeze(-1).expand(-1, -1, last.shape[-1]))
        actions = self.action_head(readout)
        visual = torch.zeros_like(valid)
        visual[:, 1 : 1 + self.num_visual_tokens] = True
        loss = None
        if "actions" in batch:
            loss = F.l1_loss(actions, batch["actions"].to(actions.dtype))
        logits = self.language_head(last) if request.lm_logits else None
        grid = self.vision_backbone.grid
        return VLAOutput(
            actions=actions,
            loss=loss,
            hidden_states=hidden,
            visual_token_mask=visual,
            attention_mask=valid,
            visual_grid=(grid, grid),
            lm_logits=logits,
        )

    def _layer_masks(self, mask: Tensor) -> Tensor | dict[str, Tensor]:
        """The additive (B, 1, S, S) mask as the decoder takes it. Gemma-3 takes one per layer type
        (transformers' ``Gemma3TextModel`` uses a given mapping as is): its local layers see only
        keys within ``sliding_window`` positions, as ``create_sliding_window_causal_mask`` and the
        bidirectional ``_bidirectional_window_overlay`` of transformers' gemma3 build them."""
        window = self.config.llm.sliding_window
        if self.config.llm.architecture != "gemma3":
            return mask
        seq = mask.shape[-1]
        offsets = torch.arange(seq, device=mask.device)
        far = (offsets[:, None] - offsets[None, :]).abs() >= window
        local = mask.masked_fill(far, torch.finfo(mask.dtype).min)
        return {"full_attention": mask, "sliding_attention": local}

    def _prefix_tokens(self, batch: Batch, language: Tensor | None = None) -> Tensor:
        """(B, n_visual [+ 1 proprio], H): projected patch tokens of every camera, then proprio.

        ``language`` (B, H): the mean language embedding FiLM conditions on (OFT+ only).
        """
        images: Tensor = batch["images"]
        b, n_cam = images.shape[:2]
        check_cameras(images, self.config.num_images)
        flat = images.flatten(0, 1)
        size = self.config.image_size
        if flat.shape[-2:] != (size, size):
            flat = F.interpolate(
                flat, size=(size, size), mode="bicubic", align_corners=False, antialias=True
            )
            flat = flat.clamp(0, 1)
        if language is not None:  # every camera of a sample sees its sample's language
            language = language.repeat_interleave(n_cam, dim=0)
        dtype = self.projector.fc1.weight.dtype
        if isinstance(self.vision_backbone, EfficientNetVision):
            dtype = self.vision_backbone.model.conv_stem.weight.dtype  # frozen: maybe bf16
        patches = self.vision_backbone(flat.to(dtype), language)
        patches = patches.to(self.projector.fc1.weight.dtype)
        visual = self.projector(patches.reshape(b, -1, patches.shape[-1]))
        if self.proprio_projector is None:
            return visual
        proprio = self.proprio_projector(batch["proprio"].to(visual.dtype)).unsqueeze(1)
        return torch.cat([visual, proprio], dim=1)

    def _embed_inputs(self, batch: Batch) -> tuple[Tensor, Tensor, Tensor, int]:
        """Input embeddings (B, S, H), valid mask (B, S), action-slot positions (B, T*A)."""
        device = batch["images"].device
        ids, text_valid, slot_pos = self._tokenize(batch["instruction"], device)
        text = self.language_model.get_input_embeddings()(ids)
        slot_mask = torch.zeros_like(ids, dtype=torch.bool).scatter_(1, slot_pos, True)
        language = _mean_embedding(text, text_valid & ~slot_mask) if self.config.film else None
        prefix_tokens = self._prefix_tokens(batch, language)
        # Continuous-action mode: action-slot embeddings are zeroed, the slots carry position only.
        text = text * (~slot_mask).unsqueeze(-1).to(text.dtype)
        embeds, valid = _splice_after_bos(text, text_valid, prefix_tokens)
        n_prefix = prefix_tokens.shape[1]
        return embeds, valid, slot_pos + n_prefix, n_prefix

    def language_head(self, hidden: Tensor, vocabulary: Tensor | None = None) -> Tensor:
        head = self.language_model.lm_head
        return project_onto_vocabulary(hidden, head.weight, head.bias, vocabulary)

    def answer_label_ids(self, answer: str) -> list[int]:
        return answer_ids_then_eos(self.require_tokenizer(), answer)

    def text_pass(
        self, batch: Batch, prompts: list[str], answers: list[str]
    ) -> tuple[Tensor, Tensor]:
        """A causal pass over ``[BOS] [visual] [proprio] prompt answer [</s>]``.

        Causal, unlike the action pass: this is the VLM's own next-token objective (StarVLA's VLM
        co-training), run separately so the action pathway's bidirectional attention is untouched.
        """
        tok = self.require_tokenizer()
        device = batch["images"].device
        rows, label_rows = [], []
        for prompt, answer in zip(prompts, answers, strict=True):
            prompt_ids = tok(prompt, add_special_tokens=False)["input_ids"]
            answer_ids = self.answer_label_ids(answer)
            rows.append([tok.bos_token_id, *prompt_ids, *answer_ids])
            label_rows.append([IGNORE_INDEX] * (1 + len(prompt_ids)) + answer_ids)
        ids, text_valid = right_pad(rows, tok.pad_token_id, device)
        text_labels, _ = right_pad(label_rows, IGNORE_INDEX, device)
        text = self.language_model.get_input_embeddings()(ids)
        # Upstream has no text pass with FiLM; this one conditions on BOS and the prompt, as OFT
        # conditions on every non-action token of its row. Not on the answer: the visual tokens
        # precede it, so every answer position would see the tokens it is trained to predict.
        prompt_only = text_valid & (text_labels == IGNORE_INDEX)
        language = _mean_embedding(text, prompt_only) if self.config.film else None
        prefix_tokens = self._prefix_tokens(batch, language)
        embeds, valid = _splice_after_bos(text, text_valid, prefix_tokens)
        n_prefix = prefix_tokens.shape[1]
        labels = torch.cat(
            [
                text_labels[:, :1],
                text_labels.new_full((ids.shape[0], n_prefix), IGNORE_INDEX),
                text_labels[:, 1:],
            ],
            1,
        )
        seq = valid.shape[1]
        causal = torch.ones(seq, seq, dtype=torch.bool, device=valid.device).tril()
        allowed = causal[None, None] & valid[:, None, None, :]
        mask = torch.zeros(allowed.shape, dtype=embeds.dtype, device=valid.device)
        mask.masked_fill_(~allowed, torch.finfo(embeds.dtype).min)
        positions = torch.arange(seq, device=valid.device).expand(valid.shape[0], -1)
        hidden = self.language_model.model(
            inputs_embeds=embeds,
            attention_mask=self._layer_masks(mask),
            position_ids=positions,
            use_cache=False,
        )
        return hidden.last_hidden_state, labels

    def _tokenize(
        self, instructions: list[str], device: torch.device
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Right-padded ``[BOS] prompt [T*A slots] [</s>]`` ids, valid mask, slot positions."""
        tok = self.require_tokenizer()
        n_slots = self.config.chunk_size * self.config.action_dim
        rows = []
        for instruction in instructions:
            prompt = self.config.prompt_template.format(instruction=instruction.lower().strip())
            ids = tok(prompt, add_special_tokens=False)["input_ids"]
            rows.append([tok.bos_token_id, *ids, *([tok.pad_token_id] * n_slots), tok.eos_token_id])
        ids, valid = right_pad(rows, tok.pad_token_id, device)
        starts = torch.tensor([len(r) - 1 - n_slots for r in rows], device=device)
        slots = starts[:, None] + torch.arange(n_slots, device=device)
        return ids, valid, slots


def _mean_embedding(text: Tensor, keep: Tensor) -> Tensor:
    """(B, S, H) embeddings averaged over the ``keep`` (B, S) positions -> (B, H).

    FiLM's language input: OFT averages ``input_embeddings[~all_actions_mask]``
    (``modeling_prismatic.py``), i.e. every token but the action slots, so BOS, the prompt and
    ``</s>``. Padding is left out here; upstream averages the pad embeddings of a padded training
    batch in too, which makes a sample's conditioning depend on its batch neighbours (a deviation
    only for padded rows: upstream's inference runs one unpadded row).
    """
    weights = keep.to(text.dtype).unsqueeze(-1)
    return (text * weights).sum(1) / weights.sum(1)


def _splice_after_bos(text: Tensor, text_valid: Tensor, prefix: Tensor) -> tuple[Tensor, Tensor]:
    """Insert the visual/proprio tokens right after BOS, as Prismatic does."""
    embeds = torch.cat([text[:, :1], prefix, text[:, 1:]], dim=1)
    ones = text_valid.new_ones(prefix.shape[:2])
    return embeds, torch.cat([text_valid[:, :1], ones, text_valid[:, 1:]], dim=1)


def _build_language_model(llm: LlamaSpec, init: bool = True) -> nn.Module:
    """Llama (OpenVLA) or Gemma-3 (the mini) as transformers builds it, attention through SDPA with
    the explicit masks ``forward`` passes (bidirectional for the action pass); with ``init``
    false, weights are left uninitialised (the caller loads every one of them)."""
    if not init:
        from transformers.initialization import no_init_weights

        with no_init_weights():
            model = _build_language_model(llm)
        model.tie_weights()
        return model
    if llm.architecture == "gemma3":
        from transformers import Gemma3ForCausalLM, Gemma3TextConfig

        config = Gemma3TextConfig(
            vocab_size=llm.vocab_size,
            hidden_size=llm.hidden_size,
            intermediate_size=llm.intermediate_size,
            num_hidden_layers=llm.num_layers,
            num_attention_heads=llm.num_heads,
            num_key_value_heads=llm.num_kv_heads,
            head_dim=llm.head_dim,
            query_pre_attn_scalar=llm.head_dim,
            max_position_embeddings=llm.max_position_embeddings,
            rms_norm_eps=llm.rms_norm_eps,
            sliding_window=llm.sliding_window,
            rope_parameters={
                "full_attention": {"rope_type": "default", "rope_theta": llm.rope_theta},
                "sliding_attention": {"rope_type": "default", "rope_theta": llm.local_rope_theta},
            },
            tie_word_embeddings=True,
            pad_token_id=0,
            bos_token_id=2,
            eos_token_id=1,
        )
        config._attn_implementation = "sdpa"
        return Gemma3ForCausalLM(config)
    if llm.architecture != "llama":
        raise BackboneError(f"llm.architecture {llm.architecture!r} is not 'llama' or 'gemma3'")
    from transformers import LlamaConfig, LlamaForCausalLM

    llama_config = LlamaConfig(
        vocab_size=llm.vocab_size,
        hidden_size=llm.hidden_size,
        intermediate_size=llm.intermediate_size,
        num_hidden_layers=llm.num_layers,
        num_attention_heads=llm.num_heads,
        num_key_value_heads=llm.num_kv_heads,
        max_position_embeddings=llm.max_position_embeddings,
        rms_norm_eps=llm.rms_norm_eps,
        rope_theta=llm.rope_theta,
        tie_word_embeddings=False,
        pad_token_id=None,
        bos_token_id=1,
        eos_token_id=2,
    )
    # SDPA with an explicit 4-D mask: the mask below makes attention bidirectional.
    llama_config._attn_implementation = "sdpa"
    return LlamaForCausalLM(llama_config)


PACKAGED_TOKENIZER = "gemma3-270m"
"""The tokenizer the packaged GGUF carries (capvector.backbones.packaged)."""


@functools.cache
def _packaged_tokenizer() -> Any:
    """Gemma's tokenizer from the dequantised cache, read once per process (262 k tokens: seconds
    per read; nothing mutates it)."""
    from capvector.backbones.packaged import gemma3_270m_tokenizer_folder
    from capvector.backbones.tokenizers import saved_tokenizer

    return saved_tokenizer(gemma3_270m_tokenizer_folder(), f"rebuild {PACKAGED_TOKENIZER}'s cache")


def _make_tokenizer(spec: str) -> Any:
    from capvector.backbones.tokenizers import byte_level_tokenizer, saved_tokenizer

    if spec == "byte":
        return byte_level_tokenizer()
    if spec == PACKAGED_TOKENIZER:
        return _packaged_tokenizer()
    tok = saved_tokenizer(spec, "point `tokenizer` at an OpenVLA-OFT checkpoint folder")
    if tok.pad_token is None:  # Prismatic adds <PAD> = 32000 to Llama-2's tokenizer
        tok.add_special_tokens({"pad_token": "<PAD>"})
    return tok


__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "SIGLIP_MEAN",
    "SIGLIP_STD",
    "EfficientNetVision",
    "FiLM",
    "FusedProjector",
    "FusedVisionBackbone",
    "L1RegressionActionHead",
    "MLPProjector",
    "OpenVLAOFT",
    "ProprioProjector",
]
