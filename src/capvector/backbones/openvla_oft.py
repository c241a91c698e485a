"""OpenVLA-OFT-style backbone: fused DINOv2 + SigLIP vision, Llama with bidirectional attention,
parallel decoding of an action chunk and an MLP-ResNet L1 head.

Faithful to moojink/openvla-oft (``prismatic/extern/hf/modeling_prismatic.py``,
``prismatic/models/action_heads.py``, ``prismatic/models/projectors.py``, ``vla-scripts/finetune.py``)
and its transformers fork (bidirectional SDPA attention). Parameter names match the released
checkpoints so they load through a small key map (``_ORIGINAL_KEY_RENAMES``).

Sequence layout (one row, right padded):
``[BOS] [N_cam x patches visual tokens] [proprio token] [prompt] [T*A action slots] [</s>] [pad]``
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from capvector.backbones.base import (
    BackboneConfig,
    BackboneError,
    OriginalCheckpoint,
    OutputRequest,
    VLABackbone,
    VLAOutput,
    keep_hidden_states,
    load_state_dict_strictly,
    nested_config,
    read_sharded,
    register_family,
    register_preset,
)
from capvector.data import keys

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SIGLIP_MEAN = (0.5, 0.5, 0.5)
SIGLIP_STD = (0.5, 0.5, 0.5)


@nested_config
@dataclass
class ViTConfig:
    """A timm VisionTransformer; the full-size values reproduce timm's DINOv2 / SigLIP models."""

    patch_size: int = 14
    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    reg_tokens: int = 0
    class_token: bool = True
    no_embed_class: bool = False
    layer_scale_init: float | None = None
    global_pool: str = "token"
    """'map' builds SigLIP's attention-pool head: unused by OFT but part of its checkpoints."""
    act_layer: str = "gelu"


@nested_config
@dataclass
class LlamaSpec:
    hidden_size: int = 4096
    intermediate_size: int = 11008
    num_layers: int = 32
    num_heads: int = 32
    num_kv_heads: int = 32
    vocab_size: int = 32064
    rope_theta: float = 10000.0
    max_position_embeddings: int = 2048
    rms_norm_eps: float = 1e-6


@dataclass
class OpenVLAOFTConfig(BackboneConfig):
    family = "openvla-oft"

    featurizer: ViTConfig = field(default_factory=ViTConfig)
    """DINOv2 half of the fused vision backbone."""
    fused_featurizer: ViTConfig = field(default_factory=ViTConfig)
    """SigLIP half of the fused vision backbone."""
    llm: LlamaSpec = field(default_factory=LlamaSpec)
    head_blocks: int = 2
    """Residual blocks of the MLP-ResNet L1 head (2 in OpenVLA-OFT)."""
    tokenizer: str = "byte"
    """'byte' builds a local byte-level tokenizer; a folder path loads a saved HF tokenizer."""
    prompt_template: str = "In: What action should the robot take to {instruction}?\nOut: "
    pad_to_multiple_of: int = 64


@register_preset("openvla-oft-7b")
def openvla_oft_7b() -> OpenVLAOFTConfig:
    """The published LIBERO configuration: 2 cameras at 224 px, 8-d proprio, chunk 8 x 7."""
    return OpenVLAOFTConfig(
        image_size=224,
        featurizer=ViTConfig(
            patch_size=14, embed_dim=1024, depth=24, num_heads=16, reg_tokens=4,
            no_embed_class=True, layer_scale_init=1e-5,
        ),
        fused_featurizer=ViTConfig(
            patch_size=14, embed_dim=1152, depth=27, num_heads=16, mlp_ratio=3.7362,
            class_token=False, global_pool="map", act_layer="gelu_tanh",
        ),
        llm=LlamaSpec(),
        tokenizer="",  # Llama-2's tokenizer comes with the checkpoint folder
    )  # fmt: skip


@register_preset("openvla-oft-tiny")
def openvla_oft_tiny() -> OpenVLAOFTConfig:
    """Same architecture at toy width: trains on a 2-core CPU in seconds (64 px, 8x8 patches)."""
    return OpenVLAOFTConfig(
        image_size=64,
        featurizer=ViTConfig(
            patch_size=8, embed_dim=48, depth=3, num_heads=4, reg_tokens=4,
            no_embed_class=True, layer_scale_init=1e-5,
        ),
        fused_featurizer=ViTConfig(
            patch_size=8, embed_dim=48, depth=3, num_heads=4, class_token=False,
            global_pool="map", act_layer="gelu_tanh",
        ),
        llm=LlamaSpec(
            hidden_size=64, intermediate_size=128, num_layers=4, num_heads=4, num_kv_heads=4,
            vocab_size=320, max_position_embeddings=512,
        ),
    )  # fmt: skip


def _build_vit(spec: ViTConfig, image_size: int) -> nn.Module:
    from timm.models.vision_transformer import VisionTransformer

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
    )


class FusedVisionBackbone(nn.Module):
    """DINOv2 + SigLIP patch features of the second-to-last block, concatenated per patch.

    As Prismatic's ``PrismaticVisionBackbone``: prefix tokens dropped, no final norm, each image
    normalised twice (ImageNet statistics for DINOv2, 0.5/0.5 for SigLIP).
    """

    def __init__(self, config: OpenVLAOFTConfig) -> None:
        super().__init__()
        self.featurizer = _build_vit(config.featurizer, config.image_size)
        self.fused_featurizer = _build_vit(config.fused_featurizer, config.image_size)
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

    def forward(self, images: Tensor) -> Tensor:
        """(B', 3, H, W) in [0, 1] -> (B', patches, D_dino + D_siglip)."""
        features = []
        for vit, mean, std in (
            (self.featurizer, self.dino_mean, self.dino_std),
            (self.fused_featurizer, self.siglip_mean, self.siglip_std),
        ):
            (out,) = vit.forward_intermediates(
                (images - mean) / std,
                indices=[len(vit.blocks) - 2],
                norm=False,
                stop_early=True,
                output_fmt="NLC",
                intermediates_only=True,
            )
            features.append(out)
        return torch.cat(features, dim=-1)


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


class MLPResNetBlock(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.ffn = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim), nn.ReLU())

    def forward(self, x: Tensor) -> Tensor:
        return x + self.ffn(x)


class MLPResNet(nn.Module):
    def __init__(self, num_blocks: int, input_dim: int, hidden_dim: int, output_dim: int) -> None:
        super().__init__()
        self.layer_norm1 = nn.LayerNorm(input_dim)
        self.fc1 = nn.Linear(input_dim, hidden_dim)
        self.relu = nn.ReLU()
        self.mlp_resnet_blocks = nn.ModuleList(
            MLPResNetBlock(hidden_dim) for _ in range(num_blocks)
        )
        self.layer_norm2 = nn.LayerNorm(hidden_dim)
        self.fc2 = nn.Linear(hidden_dim, output_dim)

    def forward(self, x: Tensor) -> Tensor:
        x = self.relu(self.fc1(self.layer_norm1(x)))
        for block in self.mlp_resnet_blocks:
            x = block(x)
        return self.fc2(self.layer_norm2(x))


class L1RegressionActionHead(nn.Module):
    """The A hidden states of one timestep, concatenated, -> MLP-ResNet -> A action values."""

    def __init__(self, llm_dim: int, action_dim: int, num_blocks: int) -> None:
        super().__init__()
        self.action_dim = action_dim
        self.model = MLPResNet(num_blocks, action_dim * llm_dim, llm_dim, action_dim)

    def forward(self, hidden: Tensor) -> Tensor:
        """(B, T*A, H) -> (B, T, A)."""
        batch, slots, width = hidden.shape
        return self.model(hidden.reshape(batch, slots // self.action_dim, self.action_dim * width))


@register_family
class OpenVLAOFT(VLABackbone):
    config_class = OpenVLAOFTConfig

    # peft full-match regex: OFT uses "all-linear" (every Linear of the LLM, both ViTs and the
    # projector). We leave out SigLIP's attention-pool head: its output is never used, so its LoRA
    # would get no gradient (the reason OFT needs DDP's find_unused_parameters=True).
    @property
    def lora_target_modules(self) -> str:  # type: ignore[override]
        # The last block of each ViT never runs (features come from the one before), so it gets
        # no LoRA either.
        def blocks(spec: ViTConfig) -> str:
            return "|".join(str(i) for i in range(spec.depth - 1))

        return (
            r".*(language_model\.model\.layers\.\d+\.(self_attn\.[qkvo]_proj|mlp\.(gate|up|down)_proj)"
            rf"|vision_backbone\.featurizer\.blocks\.({blocks(self.config.featurizer)})\.(attn\.(qkv|proj)|mlp\.fc[12])"
            rf"|vision_backbone\.fused_featurizer\.blocks\.({blocks(self.config.fused_featurizer)})\.(attn\.(qkv|proj)|mlp\.fc[12])"
            r"|projector\.fc[123])"
        )

    lora_trainable_modules = ("action_head.*", "proprio_projector.*")
    capability_parameters = ("vision_backbone.*", "projector.*", "language_model.*")

    def __init__(self, config: OpenVLAOFTConfig) -> None:
        from transformers import LlamaConfig, LlamaForCausalLM

        super().__init__(config)
        self.config: OpenVLAOFTConfig = config
        if config.image_size % config.featurizer.patch_size:
            raise BackboneError(
                f"image_size {config.image_size} is not a multiple of patch size "
                f"{config.featurizer.patch_size}"
            )
        self._tokenizer = _make_tokenizer(config.tokenizer) if config.tokenizer else None
        self.vision_backbone = FusedVisionBackbone(config)
        llm = config.llm
        self.projector = FusedProjector(self.vision_backbone.embed_dim, llm.hidden_size)
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
        self.language_model = LlamaForCausalLM(llama_config)
        self.proprio_projector = (
            ProprioProjector(config.proprio_dim, llm.hidden_size) if config.proprio_dim else None
        )
        self.action_head = L1RegressionActionHead(
            llm.hidden_size, config.action_dim, config.head_blocks
        )

    # -- contract ----------------------------------------------------------------------------

    @property
    def num_layers(self) -> int:
        return self.config.llm.num_layers

    @property
    def hidden_size(self) -> int:
        return self.config.llm.hidden_size

    def make_tokenizer(self, folder: str) -> Any:
        return _make_tokenizer(folder)

    def unused_parameter_names(self) -> list[str]:
        # Features come from the second-to-last ViT block without the final norm, and SigLIP's
        # attention-pool head is never called: these exist only so released checkpoints load.
        unused = []
        for name in ("featurizer", "fused_featurizer"):
            vit = getattr(self.vision_backbone, name)
            last = len(vit.blocks) - 1
            prefix = f"vision_backbone.{name}."
            for param_name, _ in vit.named_parameters():
                if param_name.startswith(
                    (f"blocks.{last}.", "norm.", "attn_pool.", "fc_norm.", "head.")
                ):
                    unused.append(prefix + param_name)
        return unused

    def language_head_parameter_names(self) -> list[str]:
        return [
            f"language_model.lm_head.{n}" for n, _ in self.language_model.lm_head.named_parameters()
        ]

    def shard_units(self) -> list[nn.Module]:
        vision = self.vision_backbone
        return [
            *vision.featurizer.blocks,
            *vision.fused_featurizer.blocks,
            *self.language_model.model.layers,
        ]

    @property
    def num_visual_tokens(self) -> int:
        return self.config.num_images * self.vision_backbone.grid**2

    def forward(self, batch: Mapping[str, Any], request: OutputRequest | None = None) -> VLAOutput:
        request = request or OutputRequest()
        images: Tensor = batch[keys.IMAGES]
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
                inputs_embeds=embeds, attention_mask=mask, position_ids=positions, use_cache=False
            ).last_hidden_state
        # Readout one position before each action slot: the next-token shift OFT keeps even with
        # bidirectional attention (finetune.py slices hidden states with labels[:, 1:]).
        readout = torch.gather(last, 1, (slot_pos - 1).unsqueeze(-1).expand(-1, -1, last.shape[-1]))
        actions = self.action_head(readout)
        visual = torch.zeros_like(valid)
        visual[:, 1 : 1 + self.num_visual_tokens] = True
        loss = None
        if keys.ACTIONS in batch:
            loss = F.l1_loss(actions, batch[keys.ACTIONS].to(actions.dtype))
        logits = self.language_model.lm_head(last) if request.lm_logits else None
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

    def _prefix_tokens(self, batch: Mapping[str, Any]) -> Tensor:
        """(B, n_visual [+ 1 proprio], H): projected patch tokens of every camera, then proprio."""
        images: Tensor = batch[keys.IMAGES]
        b, n_cam = images.shape[:2]
        if n_cam != self.config.num_images:
            raise BackboneError(
                f"batch has {n_cam} camera(s) but the backbone was built for "
                f"num_images={self.config.num_images}; set it to the dataset's camera count"
            )
        flat = images.flatten(0, 1)
        size = self.config.image_size
        if flat.shape[-2:] != (size, size):
            flat = F.interpolate(
                flat, size=(size, size), mode="bicubic", align_corners=False, antialias=True
            )
            flat = flat.clamp(0, 1)
        patches = self.vision_backbone(flat.to(self.projector.fc1.weight.dtype))
        visual = self.projector(patches.reshape(b, -1, patches.shape[-1]))
        if self.proprio_projector is None:
            return visual
        proprio = self.proprio_projector(batch[keys.PROPRIO].to(visual.dtype)).unsqueeze(1)
        return torch.cat([visual, proprio], dim=1)

    def _embed_inputs(self, batch: Mapping[str, Any]) -> tuple[Tensor, Tensor, Tensor, int]:
        """Input embeddings (B, S, H), valid mask (B, S), action-slot positions (B, T*A)."""
        prefix_tokens = self._prefix_tokens(batch)
        ids, text_valid, slot_pos = self._tokenize(batch[keys.INSTRUCTION], prefix_tokens.device)
        text = self.language_model.get_input_embeddings()(ids)
        # Continuous-action mode: action-slot embeddings are zeroed, the slots carry position only.
        slot_mask = torch.zeros_like(ids, dtype=torch.bool).scatter_(1, slot_pos, True)
        text = text * (~slot_mask).unsqueeze(-1).to(text.dtype)
        embeds, valid = _splice_after_bos(text, text_valid, prefix_tokens)
        n_prefix = prefix_tokens.shape[1]
        return embeds, valid, slot_pos + n_prefix, n_prefix

    def language_model_logits(
        self, batch: Mapping[str, Any], prompts: list[str], answers: list[str]
    ) -> tuple[Tensor, Tensor]:
        """A causal pass over ``[BOS] [visual] [proprio] prompt answer [</s>]``.

        Causal, unlike the action pass: this is the VLM's own next-token objective (StarVLA's VLM
        co-training), run separately so the action pathway's bidirectional attention is untouched.
        """
        tok = self._require_tokenizer()
        prefix_tokens = self._prefix_tokens(batch)
        rows, label_rows = [], []
        for prompt, answer in zip(prompts, answers, strict=True):
            prompt_ids = tok(prompt, add_special_tokens=False)["input_ids"]
            answer_ids = [*tok(answer, add_special_tokens=False)["input_ids"], tok.eos_token_id]
            rows.append([tok.bos_token_id, *prompt_ids, *answer_ids])
            label_rows.append([-100] * (1 + len(prompt_ids)) + answer_ids)
        ids, text_valid = _right_pad(rows, tok.pad_token_id, prefix_tokens.device)
        text_labels, _ = _right_pad(label_rows, -100, prefix_tokens.device)
        text = self.language_model.get_input_embeddings()(ids)
        embeds, valid = _splice_after_bos(text, text_valid, prefix_tokens)
        n_prefix = prefix_tokens.shape[1]
        labels = torch.cat(
            [
                text_labels[:, :1],
                text_labels.new_full((ids.shape[0], n_prefix), -100),
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
            inputs_embeds=embeds, attention_mask=mask, position_ids=positions, use_cache=False
        )
        return self.language_model.lm_head(hidden.last_hidden_state), labels

    def _require_tokenizer(self) -> Any:
        if self.tokenizer is None:
            raise BackboneError(
                "this backbone has no tokenizer: load a checkpoint folder that contains one "
                "(from_pretrained / from_original) or set tokenizer to a tokenizer folder"
            )
        return self.tokenizer

    def _tokenize(
        self, instructions: list[str], device: torch.device
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Right-padded ``[BOS] prompt [T*A slots] [</s>]`` ids, valid mask, slot positions."""
        tok = self._require_tokenizer()
        n_slots = self.config.chunk_size * self.config.action_dim
        rows = []
        for instruction in instructions:
            prompt = self.config.prompt_template.format(instruction=instruction.lower().strip())
            ids = tok(prompt, add_special_tokens=False)["input_ids"]
            rows.append([tok.bos_token_id, *ids, *([tok.pad_token_id] * n_slots), tok.eos_token_id])
        ids, valid = _right_pad(rows, tok.pad_token_id, device)
        starts = torch.tensor([len(r) - 1 - n_slots for r in rows], device=device)
        slots = starts[:, None] + torch.arange(n_slots, device=device)
        return ids, valid, slots

    # -- original OpenVLA-OFT checkpoints -----------------------------------------------------

    @classmethod
    def from_original(
        cls,
        source: str | Path,
        preset: str | None = None,
        overrides: Mapping[str, Any] | None = None,
        apply_lora_adapter: bool = False,
    ) -> OriginalCheckpoint:
        """Load a released OpenVLA-OFT run folder strictly, with its statistics.

        The folder holds merged safetensors (+ index), ``action_head--*_checkpoint.pt`` and
        ``proprio_projector--*_checkpoint.pt`` (DDP ``module.`` prefixes), ``dataset_statistics.json``
        and optionally ``lora_adapter/`` (merged into the weights with ``apply_lora_adapter``; the
        released folders already hold merged weights). A hub repo id is downloaded first.
        """
        from capvector.backbones.base import preset_config

        root = _resolve_folder(source)
        preset = preset or "openvla-oft-7b"
        config = preset_config(preset, **(overrides or {}))
        if not isinstance(config, OpenVLAOFTConfig):
            raise BackboneError(f"preset {preset!r} is not an OpenVLA-OFT preset")
        if (root / "tokenizer_config.json").is_file():
            config.tokenizer = str(root)
        model = cls(config)
        state = _read_original_vlm(root)
        state.update(_read_component(root, "action_head", "action_head."))
        if config.proprio_dim:
            state.update(_read_component(root, "proprio_projector", "proprio_projector."))
        if apply_lora_adapter:
            _merge_peft_adapter(state, root / "lora_adapter")
        load_state_dict_strictly(model, state, source=str(root))
        stats_path = root / "dataset_statistics.json"
        stats = json.loads(stats_path.read_text()) if stats_path.is_file() else {}
        return OriginalCheckpoint(model, stats)


def _right_pad(rows: list[list[int]], pad: int, device: torch.device) -> tuple[Tensor, Tensor]:
    length = max(len(r) for r in rows)
    ids = torch.full((len(rows), length), pad, dtype=torch.long)
    valid = torch.zeros((len(rows), length), dtype=torch.bool)
    for i, row in enumerate(rows):
        ids[i, : len(row)] = torch.tensor(row)
        valid[i, : len(row)] = True
    return ids.to(device), valid.to(device)


def _splice_after_bos(text: Tensor, text_valid: Tensor, prefix: Tensor) -> tuple[Tensor, Tensor]:
    """Insert the visual/proprio tokens right after BOS, as Prismatic does."""
    embeds = torch.cat([text[:, :1], prefix, text[:, 1:]], dim=1)
    ones = text_valid.new_ones(prefix.shape[:2])
    return embeds, torch.cat([text_valid[:, :1], ones, text_valid[:, 1:]], dim=1)


# LayerScale parameters are called `gamma` in timm; HF renames parameters containing "gamma", so
# Prismatic stores them as `scale_factor` (helper `ls_apply_patch`).
_ORIGINAL_KEY_RENAMES = ((".ls1.scale_factor", ".ls1.gamma"), (".ls2.scale_factor", ".ls2.gamma"))


def _make_tokenizer(spec: str) -> Any:
    if spec == "byte":
        from capvector.backbones.tokenizers import byte_level_tokenizer

        return byte_level_tokenizer()
    from transformers import AutoTokenizer

    tok = AutoTokenizer.from_pretrained(spec)
    if tok.pad_token is None:  # Prismatic adds <PAD> = 32000 to Llama-2's tokenizer
        tok.add_special_tokens({"pad_token": "<PAD>"})
    return tok


def _resolve_folder(folder: str | Path) -> Path:
    path = Path(folder)
    if path.is_dir():
        return path
    if str(folder).count("/") == 1 and not path.exists():
        try:
            from huggingface_hub import snapshot_download

            return Path(snapshot_download(str(folder)))
        except Exception as exc:  # no network, private repo, unknown id
            raise BackboneError(
                f"{folder} is not a local folder and could not be downloaded from the hub ({exc}); "
                "download it where the network allows and pass the local path"
            ) from exc
    raise BackboneError(f"checkpoint folder {folder} does not exist")


def _read_original_vlm(root: Path) -> dict[str, Tensor]:
    from safetensors.torch import load_file

    if (root / "model.safetensors.index.json").is_file():
        raw = read_sharded(root)
    elif (root / "model.safetensors").is_file():
        raw = load_file(str(root / "model.safetensors"))
    else:
        raise BackboneError(
            f"{root} has no merged VLM weights (model.safetensors or model.safetensors.index.json)"
        )
    state = {}
    for key, value in raw.items():
        for old, new in _ORIGINAL_KEY_RENAMES:
            if key.startswith("vision_backbone.") and key.endswith(old):
                key = key[: -len(old)] + new
        state[key] = value
    return state


def _read_component(root: Path, name: str, prefix: str) -> dict[str, Tensor]:
    files = sorted(root.glob(f"{name}--*checkpoint.pt"))
    if not files:
        raise BackboneError(f"{root} has no {name}--<step>_checkpoint.pt file")
    if len(files) > 1:
        raise BackboneError(
            f"{root} has several {name} files ({[f.name for f in files]}); keep one"
        )
    raw = torch.load(files[0], map_location="cpu", weights_only=True)
    # Saved from DDP-wrapped modules, hence the `module.` prefix (OFT's remove_ddp_in_checkpoint).
    return {prefix + k.removeprefix("module."): v for k, v in raw.items()}


def _merge_peft_adapter(state: dict[str, Tensor], adapter_dir: Path) -> None:
    """W += (alpha / r) * B @ A for every LoRA pair of a PEFT adapter folder."""
    from safetensors.torch import load_file

    config_path = adapter_dir / "adapter_config.json"
    if not config_path.is_file():
        raise BackboneError(f"{adapter_dir} is not a PEFT adapter folder (no adapter_config.json)")
    config = json.loads(config_path.read_text())
    weights_path = adapter_dir / "adapter_model.safetensors"
    if weights_path.is_file():
        weights = load_file(str(weights_path))
    else:
        weights = torch.load(
            adapter_dir / "adapter_model.bin", map_location="cpu", weights_only=True
        )
    scaling = config["lora_alpha"] / config["r"]
    for key, lora_a in weights.items():
        if not key.endswith(".lora_A.weight"):
            continue
        module = key.removeprefix("base_model.model.").removesuffix(".lora_A.weight")
        lora_b = weights[key.replace(".lora_A.", ".lora_B.")]
        target = f"{module}.weight"
        if target not in state:
            raise BackboneError(f"LoRA adapter targets {target}, which the checkpoint lacks")
        merged = state[target].float() + scaling * (lora_b.float() @ lora_a.float())
        state[target] = merged.to(state[target].dtype)
