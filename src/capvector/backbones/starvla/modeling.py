"""StarVLA-style backbone: a Qwen-VL (transformers' own Qwen2.5-VL or Qwen3-VL classes) plus a
pluggable action head from ``heads.py``.

Follows starVLA/starVLA: the wrappers ``starVLA/model/modules/vlm/QWen2_5.py`` / ``QWen3.py`` (one
user turn per sample with every camera image, then the text; the chat template with the generation
prompt; left padding) and the frameworks ``starVLA/model/framework/VLM4A/QwenOFT.py``,
``QwenGR00T.py``, ``QwenPI_v3.py``. Deviations, each marked where it happens:

- the Qwen class is chosen by ``qwen_version``, not by substring-matching the checkpoint path;
- OFT's action queries in a new model are a real added special token, always one token, with its
  id taken from the tokenizer (StarVLA uses an emoji that Qwen3.5's tokenizer splits into 3
  tokens). A StarVLA run imported by ``from_original`` keeps StarVLA's emoji, an ordinary single
  Qwen token: splitting a special token out of the text changes how its neighbours tokenise;
- every id (image pad, vision start/end, queries) comes from the tokenizer, none is hard-coded;
- the configured attention implementation is honoured (StarVLA's ``QWen3.py`` overrides it with sdpa);
- images are normalised and patchified in the model, on the batch's device, as transformers' Qwen
  image processors do (tested against StarVLA's outputs), instead of a PIL round trip per sample.

Followed on purpose, though surprising: under StarVLA's transformers 4.57, the heads of a Qwen3-VL
run read the last decoder layer *before* the final norm (``QwenVersion.head_reads_final_norm``).
The config and presets are in ``configuration.py``; loading StarVLA runs (config.yaml, statistics,
key map) is in ``convert.py``.

Sequence layout (one row, left padded)::

    [pad] <|im_start|>system ... <|im_end|> <|im_start|>user
    (<|vision_start|> [visual tokens] <|vision_end|>) x N_cam  prompt  [STATE] bins [ACTION]
    head suffix (OFT: "... <action>" + T x <|action_query|> + "<action>.")  <|im_end|>
    <|im_start|>assistant
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
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
    load_state_dict_strictly,
    preset_config,
    project_onto_vocabulary,
    register_family,
)
from capvector.backbones.common import check_cameras, discretize_state
from capvector.backbones.starvla.configuration import (
    QWEN_VERSIONS,
    STATE_MODES,
    QwenVersion,
    StarVLAConfig,
)
from capvector.backbones.starvla.heads import HeadDims, HeadInput, build_head, head_class
from capvector.data.batch import Batch
from capvector.io.loading import load_safetensors

# Qwen-VL's chat-format special tokens (the same strings in Qwen2-VL, Qwen2.5-VL and Qwen3-VL).
IMAGE_PAD = "<|image_pad|>"
VIDEO_PAD = "<|video_pad|>"
VISION_START = "<|vision_start|>"
VISION_END = "<|vision_end|>"
QWEN_SPECIAL_TOKENS = (
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    VISION_START,
    VISION_END,
    IMAGE_PAD,
    VIDEO_PAD,
)
HEAD_WEIGHTS_PREFIX = "action_head."


# -- tokenizer -----------------------------------------------------------------------------------

# Qwen2.5-VL's chat template (tokenizer_config.json of Qwen/Qwen2.5-VL-*-Instruct), image and text
# parts: what the tiny tokenizer renders, so prompts look like the real model's.
QWEN_CHAT_TEMPLATE = (
    "{% set image_count = namespace(value=0) %}{% for message in messages %}"
    "{% if loop.first and message['role'] != 'system' %}<|im_start|>system\n"
    "You are a helpful assistant.<|im_end|>\n{% endif %}<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}<|im_end|>\n"
    "{% else %}{% for content in message['content'] %}"
    "{% if content['type'] == 'image' or 'image' in content or 'image_url' in content %}"
    "{% set image_count.value = image_count.value + 1 %}"
    "{% if add_vision_id %}Picture {{ image_count.value }}: {% endif %}"
    "<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif 'text' in content %}{{ content['text'] }}{% endif %}{% endfor %}<|im_end|>\n"
    "{% endif %}{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)


def tiny_qwen_tokenizer() -> Any:
    """A real HF fast tokenizer with one token per byte, Qwen's special tokens and chat template."""
    from capvector.backbones.tokenizers import byte_level_tokenizer

    tok = byte_level_tokenizer()
    tok.add_special_tokens({"additional_special_tokens": list(QWEN_SPECIAL_TOKENS)})
    tok.pad_token = "<|endoftext|>"  # Qwen's pad token
    tok.chat_template = QWEN_CHAT_TEMPLATE
    return tok


def _load_tokenizer(spec: str) -> Any:
    from capvector.backbones.tokenizers import saved_tokenizer

    if spec == "tiny":
        return tiny_qwen_tokenizer()
    return saved_tokenizer(
        spec,
        "point `tokenizer` at the Qwen checkpoint folder or load the model with "
        "from_pretrained / from_qwen",
    )


@dataclass(frozen=True)
class TokenIds:
    """Ids resolved from the tokenizer (StarVLA hard-codes 151655 and friends)."""

    image_pad: int
    vision_start: int
    vision_end: int
    query: int | None


# -- the model -----------------------------------------------------------------------------------


@register_family
class StarVLA(VLABackbone):
    """Qwen-VL (``vlm``, a transformers ``*ForConditionalGeneration``) + action head (``action_head``)."""

    config_class = StarVLAConfig
    original_loader = "capvector.backbones.starvla.convert"
    missing_tokenizer_hint = (
        "load a checkpoint folder that has one (StarVLA.from_qwen / from_pretrained) or set "
        "tokenizer to a Qwen tokenizer folder"
    )
    import_options = (
        ImportOption(
            "qwen_folder",
            "the Qwen-VL folder the StarVLA run started from (without it, --folder is a plain "
            "Qwen-VL folder and the head starts fresh)",
            type=Path,
        ),
    )
    # peft full-match regex: every Linear of the Qwen language model, the vision blocks and the
    # patch mergers (Qwen2.5-VL: merger.mlp.0/2, gate/up/down MLPs; Qwen3-VL: linear_fc1/2 and the
    # deepstack mergers). lm_head is left out: it is tied to the embeddings and unused by the heads.
    lora_target_modules = (
        r"vlm\.model\.(language_model\.layers\.\d+\.(self_attn\.[qkvo]_proj|mlp\.(gate|up|down)_proj)"
        r"|visual\.blocks\.\d+\.(attn\.(qkv|proj)|mlp\.(gate_proj|up_proj|down_proj|linear_fc[12]))"
        r"|visual\.(merger|deepstack_merger_list\.\d+)\.(mlp\.[02]|linear_fc[12]))"
    )
    lora_trainable_modules = ("action_head.*",)
    capability_parameters = ("vlm.*",)

    def __init__(
        self, config: StarVLAConfig, *, vlm: nn.Module | None = None, tokenizer: Any = None
    ) -> None:
        """``vlm`` and ``tokenizer`` are passed by the loaders (already built from a checkpoint);
        otherwise the VLM is built from ``config.qwen`` with random weights."""
        super().__init__(config)
        self.config: StarVLAConfig = config
        version = _qwen_version(config.qwen_version)
        if config.state_mode not in STATE_MODES:
            raise BackboneError(f"state_mode {config.state_mode!r} is not one of {STATE_MODES}")
        if config.state_mode != "none" and not config.proprio_dim:
            raise BackboneError(f"state_mode={config.state_mode!r} needs proprio_dim > 0")
        if vlm is None and not config.qwen:
            raise BackboneError(
                "config.qwen is empty: use a starvla-* preset or StarVLA.from_qwen(folder, ...)"
            )
        config_class, model_class = version.classes()
        hf_config = vlm.config if vlm is not None else config_class(**config.qwen)
        text, vision = hf_config.text_config, hf_config.vision_config
        self.patch_size: int = vision.patch_size
        self.merge_size: int = vision.spatial_merge_size
        self.temporal_patch_size: int = vision.temporal_patch_size
        factor = self.patch_size * self.merge_size
        if config.image_size % factor:
            raise BackboneError(
                f"image_size {config.image_size} is not a multiple of patch x merge = {factor} "
                "(Qwen's smart_resize would change it); pick a multiple, e.g. 224 for Qwen2.5-VL"
            )
        dims = HeadDims(
            vlm_width=text.hidden_size,
            vlm_layers=text.num_hidden_layers,
            action_dim=config.action_dim,
            chunk_size=config.chunk_size,
            state_dim=config.proprio_dim if config.state_mode == "head" else 0,
        )
        # The head first: its config errors come before the (slow, for 4B) VLM construction.
        head = build_head(config.head, config.head_args, dims)
        attention_kernels_with_4d_masks = ("sdpa", "eager")
        if (
            head.bidirectional_queries
            and config.attn_implementation not in attention_kernels_with_4d_masks
        ):
            raise BackboneError(
                "bidirectional_queries needs a 4-D attention mask: use attn_implementation "
                f"'sdpa' or 'eager', not {config.attn_implementation!r}"
            )
        if vlm is None:
            vlm = model_class._from_config(
                hf_config, attn_implementation=config.attn_implementation, dtype=torch.float32
            )
        self.vlm = vlm
        self.action_head = head
        # Exports and checkpoints record every head field, not just the preset's overrides.
        config.head_args = head.config_dict()
        self.register_buffer(
            "pixel_mean", torch.tensor(config.image_mean).view(1, 3, 1, 1), persistent=False
        )
        self.register_buffer(
            "pixel_std", torch.tensor(config.image_std).view(1, 3, 1, 1), persistent=False
        )
        self._tokenizer: Any = None
        self._ids: TokenIds | None = None
        if tokenizer is not None:
            self._install_tokenizer(tokenizer, allow_resize=True)
        # Tied embeddings (Qwen2.5-VL-3B, Qwen3-VL-4B) are one tensor under two names. As transformers'
        # own checkpoints, our state dict holds it once, so exports load into safetensors (which
        # refuses shared tensors) and capability vectors count it once.
        self.register_state_dict_post_hook(_drop_tied_lm_head)
        self.register_load_state_dict_pre_hook(_restore_tied_lm_head)

    # -- contract ----------------------------------------------------------------------------

    @property
    def num_layers(self) -> int:
        return self.vlm.config.text_config.num_hidden_layers

    @property
    def hidden_size(self) -> int:
        return self.vlm.config.text_config.hidden_size

    @property
    def tokenizer(self) -> Any:
        if self._tokenizer is None and self.config.tokenizer:
            self._install_tokenizer(_load_tokenizer(self.config.tokenizer))
        return self._tokenizer

    def load_tokenizer(self, folder: str | Path) -> None:
        if (Path(folder) / "tokenizer_config.json").is_file():
            from capvector.backbones.tokenizers import saved_tokenizer

            self._install_tokenizer(saved_tokenizer(folder, ""))  # a cut file: one line

    @property
    def visual_grid(self) -> tuple[int, int]:
        """Visual tokens per camera after Qwen's 2x2 patch merge: (rows, cols)."""
        side = self.config.image_size // (self.patch_size * self.merge_size)
        return side, side

    @property
    def num_visual_tokens(self) -> int:
        rows, cols = self.visual_grid
        return self.config.num_images * rows * cols

    def forward(self, batch: Batch, request: OutputRequest | None = None) -> VLAOutput:
        request = request or OutputRequest()
        head = self.action_head
        encoding = self.encode(batch, request.hidden_layers, all_layers=head.uses_all_layers)
        state = _state(batch) if self.config.state_mode == "head" else None
        # The head runs in its own precision, outside autocast, as StarVLA's fp32 head region.
        head_dtype = next(head.parameters()).dtype
        cond = encoding.head_input.to(head_dtype)
        state = None if state is None else state.to(head_dtype)
        with torch.autocast(device_type=cond.mask.device.type, enabled=False):
            if "actions" in batch:
                target = batch["actions"].to(head_dtype)
                seeds = batch.get("noise_seed")  # per-sample flow noise, see draw_flow_noise
                if request.actions or head.loss_predicts_actions:
                    loss, actions = head.loss_and_actions(cond, target, state, seeds)
                else:  # training: a flow head would run every denoising step for nothing
                    loss, actions = head.loss(cond, target, state, seeds), None
            else:
                loss, actions = None, head.sample(cond, state)
        logits = self.language_head(encoding.normed_last) if request.lm_logits else None
        return VLAOutput(
            actions=actions,
            loss=loss,
            hidden_states=encoding.requested,
            visual_token_mask=encoding.input_ids == self._token_ids.image_pad,
            attention_mask=encoding.head_input.mask,
            visual_grid=self.visual_grid,
            lm_logits=logits,
        )

    # -- Qwen-VL encoding ---------------------------------------------------------------------

    def encode(
        self, batch: Batch, hidden_layers: Sequence[int] = (), all_layers: bool = False
    ) -> VLMEncoding:
        """Run the Qwen-VL on a batch: the head's conditioning and the requested hidden states.

        ``hidden_layers`` follows the contract (0 = input embeddings, k = decoder layer k before the
        final norm). ``all_layers`` also returns every layer for the head, as StarVLA's heads read
        HF's ``hidden_states[1:]`` (see ``QwenVersion.head_reads_final_norm``).
        """
        images: Tensor = batch["images"]
        n_cam = images.shape[1]
        check_cameras(images, self.config.num_images)
        instructions: list[str] = list(batch["instruction"])
        state = _state(batch) if self.config.state_mode == "prompt" else None
        texts = [
            self.prompt_text(text, None if state is None else state[i])
            for i, text in enumerate(instructions)
        ]
        ids, mask = self.tokenize(texts, n_cam, images.device)
        model = self.vlm.model
        query_positions = self._query_positions(ids)
        attention = mask
        if self.action_head.bidirectional_queries:
            attention = self._bidirectional_query_mask(mask, query_positions)
        layer_indices = set(hidden_layers)
        store: dict[int, Tensor] = {}
        # What StarVLA's heads read: HF's hidden_states[1:] (transformers 4.57). Entry k < L is
        # the input of decoder layer k + 1 (layer k's output plus any DeepStack features added
        # after it); the last is the final layer's output, normed or not by Qwen version.
        head_store: dict[int, Tensor] = {}
        layers = model.language_model.layers
        head_entries = range(1, self.num_layers) if all_layers else range(0)
        normed = _qwen_version(self.config.qwen_version).head_reads_final_norm
        hooks = []
        if 0 in layer_indices:

            def grab(_module: nn.Module, _args: Any, kwargs: dict[str, Any]) -> None:
                store[0] = kwargs["inputs_embeds"]

            hooks.append(model.language_model.register_forward_pre_hook(grab, with_kwargs=True))
        for k in head_entries:

            def enter(_module: nn.Module, args: Any, kwargs: dict[str, Any], k: int = k) -> None:
                head_store[k] = args[0] if args else kwargs["hidden_states"]

            hooks.append(layers[k].register_forward_pre_hook(enter, with_kwargs=True))
        if not normed:

            def leave(_module: nn.Module, _args: Any, output: Any) -> None:
                head_store[self.num_layers] = output[0] if isinstance(output, tuple) else output

            hooks.append(layers[-1].register_forward_hook(leave))
        try:
            with keep_hidden_states(layers, sorted(layer_indices), store):
                out = self._run_vlm(ids, mask, images, attention)
        finally:
            for hook in hooks:
                hook.remove()
        final = out.last_hidden_state
        last = final if normed else head_store[self.num_layers]
        head_layers = tuple(head_store[k] for k in head_entries) + (last,) if all_layers else ()
        return VLMEncoding(
            input_ids=ids,
            head_input=HeadInput(
                last_hidden=last, mask=mask, layers=head_layers, query_positions=query_positions
            ),
            requested={i: store[i] for i in hidden_layers},
            normed_last=final,
        )

    def prompt_text(self, instruction: str, state: Tensor | None = None) -> str:
        """The user text: template(instruction [+ STATE bins] [+ head suffix])."""
        text = instruction
        if state is not None:
            text = f"{text} [STATE] {' '.join(map(str, self.state_bins(state).tolist()))} [ACTION]"
        text += self.action_head.prompt_suffix()
        return self.config.prompt_template.replace("{instruction}", text)

    def state_bins(self, state: Tensor) -> Tensor:
        """(P,) normalised state -> bin indices, as StarVLA's ``share_tools.state2str_transform``:
        ``np.digitize(s, linspace(-1, 1, n + 1)[:-1]) - 1``. Values below -1 give bin -1 and values
        from 1 - 2/n up give n - 1, as there: StarVLA's q99 normaliser clamps states to [-2.2, 2.2]
        only (``gr00t_lerobot/transform/state_action.py``), so states outside [-1, 1] reach the
        prompt. Computed in float64, where the bin edges -1 + 2k/n are exact.
        """
        return discretize_state(state, self.config.state_bins)

    def tokenize(
        self, texts: Sequence[str], n_images: int, device: torch.device
    ) -> tuple[Tensor, Tensor]:
        """Left-padded ids (B, S) and valid mask (B, S) of one user turn per text, ending with the
        generation prompt (StarVLA's ``build_qwenvl_inputs``)."""
        tok = self.require_tokenizer()
        rendered = [self.render_chat(text, n_images) for text in texts]
        encoded = tok(rendered, padding=True, add_special_tokens=False, return_tensors="pt")
        return encoded["input_ids"].to(device), encoded["attention_mask"].to(device).bool()

    def render_chat(self, text: str, n_images: int) -> str:
        """The chat-template text of one user turn (images, then ``text``) + the generation prompt.

        As Qwen's processor, the template's single ``<|image_pad|>`` per image is then repeated
        once per visual token of that image.
        """
        content = [{"type": "image"}] * n_images + [{"type": "text", "text": text}]
        chat = self.require_tokenizer().apply_chat_template(
            [{"role": "user", "content": content}], tokenize=False, add_generation_prompt=True
        )
        if chat.count(IMAGE_PAD) != n_images:
            raise BackboneError(
                f"the tokenizer's chat template rendered {chat.count(IMAGE_PAD)} {IMAGE_PAD} for "
                f"{n_images} images; it is not a Qwen-VL chat template"
            )
        rows, cols = self.visual_grid
        return chat.replace(IMAGE_PAD, IMAGE_PAD * (rows * cols))

    def language_head(self, hidden: Tensor, vocabulary: Tensor | None = None) -> Tensor:
        head = self.vlm.lm_head
        return project_onto_vocabulary(hidden, head.weight, head.bias, vocabulary)

    def answer_label_ids(self, answer: str) -> list[int]:
        return self.require_tokenizer().encode(answer + "<|im_end|>", add_special_tokens=False)

    def text_pass(
        self, batch: Batch, prompts: list[str], answers: list[str]
    ) -> tuple[Tensor, Tensor]:
        """Qwen's own LM head over a user turn (cameras + prompt) and an assistant turn (answer),
        as StarVLA's VLM co-training (``build_qwenvl_inputs(..., solutions=...)``).

        Labels are IGNORE_INDEX except on the answer tokens and the ``<|im_end|>`` closing the turn; rows
        are left padded like the action pass. The prompt carries no action queries or state: this
        is the VLM's plain next-token objective.
        """
        tok = self.require_tokenizer()
        images: Tensor = batch["images"]
        n_cam = images.shape[1]
        rows, label_rows = [], []
        for prompt, answer in zip(prompts, answers, strict=True):
            prompt_ids = tok.encode(self.render_chat(prompt, n_cam), add_special_tokens=False)
            answer_ids = self.answer_label_ids(answer)
            rows.append(prompt_ids + answer_ids)
            label_rows.append([IGNORE_INDEX] * len(prompt_ids) + answer_ids)
        length = max(len(r) for r in rows)
        ids = torch.full((len(rows), length), tok.pad_token_id, dtype=torch.long)
        labels = torch.full((len(rows), length), IGNORE_INDEX, dtype=torch.long)
        for i, (row, label) in enumerate(zip(rows, label_rows, strict=True)):
            ids[i, length - len(row) :] = torch.tensor(row)
            labels[i, length - len(row) :] = torch.tensor(label)
        ids, labels = ids.to(images.device), labels.to(images.device)
        mask = ids.new_zeros(ids.shape, dtype=torch.bool)
        for i, row in enumerate(rows):
            mask[i, length - len(row) :] = True
        out = self._run_vlm(ids, mask, images)
        return out.last_hidden_state, labels

    def _run_vlm(
        self, ids: Tensor, mask: Tensor, images: Tensor, attention: Tensor | None = None
    ) -> Any:
        """The Qwen-VL base model (no LM head) over ``ids`` with the batch's images.

        ``mask`` (B, S) gives the multimodal RoPE positions; ``attention`` optionally replaces it
        with a 4-D mask. Positions are computed here rather than inside transformers so that a 4-D
        mask can be passed and no ``rope_deltas`` state is cached on the module between calls.
        """
        pixel_values, grid_thw = self.pixel_values(images)
        image_tokens = (ids == self._token_ids.image_pad).int()
        position_ids, _ = self.vlm.model.get_rope_index(
            ids, mm_token_type_ids=image_tokens, image_grid_thw=grid_thw, attention_mask=mask
        )
        return self.vlm.model(
            input_ids=ids,
            attention_mask=mask if attention is None else attention,
            position_ids=position_ids,
            pixel_values=pixel_values.to(self.vlm.dtype),
            image_grid_thw=grid_thw,
            mm_token_type_ids=image_tokens,
            use_cache=False,
        )

    def shard_units(self) -> list[nn.Module]:
        model = self.vlm.model
        blocks = getattr(getattr(self.action_head, "model", None), "transformer_blocks", [])
        return [*model.visual.blocks, *model.language_model.layers, *blocks]

    def pixel_values(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """(B, N_cam, 3, H, W) in [0, 1] -> Qwen's flat patches and ``image_grid_thw``.

        Same layout as transformers' ``Qwen2VLImageProcessor.patchify``: per image, patches in
        (row-block, col-block, 2x2 merge window) order, each repeated ``temporal_patch_size`` times.
        """
        flat = images.flatten(0, 1).float()
        size = self.config.image_size
        if flat.shape[-2:] != (size, size):
            flat = _resize_8bit(flat, size)
        flat = (flat - self.pixel_mean) / self.pixel_std
        n, channels = flat.shape[:2]
        p, m, t = self.patch_size, self.merge_size, self.temporal_patch_size
        grid = size // p
        patches = flat.reshape(n, channels, grid // m, m, p, grid // m, m, p)
        patches = patches.permute(0, 2, 5, 3, 6, 1, 4, 7).unsqueeze(6)
        patches = patches.expand(-1, -1, -1, -1, -1, -1, t, -1, -1)
        pixel_values = patches.reshape(n * grid * grid, channels * t * p * p)
        grid_thw = torch.tensor([[1, grid, grid]] * n, device=images.device)
        return pixel_values, grid_thw

    def _query_positions(self, ids: Tensor) -> Tensor | None:
        n = self.action_head.num_query_tokens
        if not n:
            return None
        is_query = ids == self._token_ids.query
        counts = is_query.sum(1)
        if (counts != n).any():
            raise BackboneError(
                f"every prompt must hold exactly {n} action query tokens "
                f"{self.action_head.query_token!r}; counts per sample: {counts.tolist()} (does an "
                "instruction contain the token text?)"
            )
        return is_query.nonzero()[:, 1].view(ids.shape[0], n)

    def _bidirectional_query_mask(self, mask: Tensor, query_positions: Tensor | None) -> Tensor:
        """(B, 1, S, S) mask: causal + padding, except that the query block attends to itself in
        both directions, as OpenVLA-OFT's action slots (StarVLA keeps it causal). Boolean for sdpa
        (True = attend), additive for eager attention, the formats transformers builds itself."""
        length = mask.shape[1]
        causal = torch.ones(length, length, dtype=torch.bool, device=mask.device).tril()
        allowed = causal[None] & mask[:, None, :]
        if query_positions is not None:
            is_query = torch.zeros_like(mask).scatter_(1, query_positions, True)
            allowed = allowed | (is_query[:, :, None] & is_query[:, None, :])
        # Padded rows attend to themselves only: no row is empty, so no NaN from the softmax.
        allowed = (allowed | torch.eye(length, dtype=torch.bool, device=mask.device))[:, None]
        if self.config.attn_implementation == "sdpa":
            return allowed
        dtype = self.vlm.dtype
        additive = torch.zeros(allowed.shape, dtype=dtype, device=mask.device)
        return additive.masked_fill_(~allowed, torch.finfo(dtype).min)

    # -- tokenizer installation ---------------------------------------------------------------

    @property
    def _token_ids(self) -> TokenIds:
        self.require_tokenizer()  # installs a configured tokenizer on first use
        assert self._ids is not None  # resolved with every tokenizer
        return self._ids

    def _install_tokenizer(self, tok: Any, allow_resize: bool = False) -> None:
        """Resolve every id from ``tok``; add the head's query token as a special token.

        ``allow_resize`` (only while building from a Qwen checkpoint) grows the embeddings when the
        tokenizer outgrows them; later the vocabulary in ``config.qwen`` already has the room.
        """
        # Left padding, as StarVLA's wrappers: prompts end at the same column.
        tok.padding_side = "left"
        if tok.pad_token is None:
            raise BackboneError(
                "the tokenizer has no pad token; a Qwen tokenizer uses <|endoftext|>"
            )
        if not getattr(tok, "chat_template", None):
            raise BackboneError("the tokenizer has no chat template; use a Qwen-VL tokenizer")
        specials = {}
        for token in (IMAGE_PAD, VISION_START, VISION_END):
            ids = tok.encode(token, add_special_tokens=False)
            if len(ids) != 1:
                raise BackboneError(f"the tokenizer has no {token} token: not a Qwen-VL tokenizer")
            specials[token] = ids[0]
        query = None
        head = self.action_head
        if head.num_query_tokens:
            (query,) = self._add_special_tokens(tok, [head.query_token])
        self._fit_embeddings(tok, allow_resize)
        for name, token in (
            ("image_token_id", IMAGE_PAD),
            ("vision_start_token_id", VISION_START),
            ("vision_end_token_id", VISION_END),
        ):
            setattr(self.vlm.config, name, specials[token])
        self._ids = TokenIds(
            specials[IMAGE_PAD], specials[VISION_START], specials[VISION_END], query
        )
        self._tokenizer = tok

    def add_action_tokens(self, tokens: Sequence[str]) -> range:
        """Add ``tokens`` as special tokens (where missing) and return their id range, resolved
        from the tokenizer (StarVLA hard-codes 151665-153712 for its ``<robot_action_k>``). Grows
        the embeddings when the vocabulary is full; call it before training or loading weights."""
        tok = self.require_tokenizer()
        ids = self._add_special_tokens(tok, tokens)
        self._fit_embeddings(tok, allow_resize=True)
        if ids != list(range(ids[0], ids[0] + len(ids))):
            raise BackboneError(f"tokens {list(tokens)[:3]}... did not get consecutive ids")
        return range(ids[0], ids[0] + len(ids))

    @staticmethod
    def _add_special_tokens(tok: Any, tokens: Sequence[str]) -> list[int]:
        from tokenizers import AddedToken

        # A token the tokenizer already encodes as one id is used as it is: StarVLA's emoji query
        # is an ordinary token of Qwen's vocabulary, and adding it as a special token would change
        # how its neighbours are split (``>🔍🔍<`` is one pre-token in Qwen's pattern).
        missing = [t for t in tokens if len(tok.encode(t, add_special_tokens=False)) != 1]
        if missing:
            # Special added tokens: never split, never merged with their neighbours.
            tok.add_tokens(
                [AddedToken(t, special=True, normalized=False) for t in missing],
                special_tokens=True,
            )
        ids = []
        for token in tokens:
            encoded = tok.encode(token, add_special_tokens=False)
            if len(encoded) != 1:
                raise BackboneError(f"token {token!r} encodes to {len(encoded)} tokens, not one")
            ids.append(encoded[0])
        return ids

    def _fit_embeddings(self, tok: Any, allow_resize: bool) -> None:
        vocab = self.vlm.get_input_embeddings().num_embeddings
        if len(tok) > vocab:
            if not allow_resize:
                raise BackboneError(
                    f"the tokenizer has {len(tok)} tokens but the embeddings only {vocab}: load "
                    "the tokenizer saved with these weights"
                )
            self.vlm.resize_token_embeddings(len(tok), pad_to_multiple_of=64)
            self.config.qwen["text_config"]["vocab_size"] = self.vlm.config.text_config.vocab_size

    # -- loading -----------------------------------------------------------------------------

    def save_head_weights(self, path: str | Path) -> Path:
        """The head's parameters alone, as one safetensors file (keys relative to the head)."""
        from safetensors.torch import save

        from capvector.io.outputs import atomic_write_bytes

        state = {k: v.detach().cpu().contiguous() for k, v in self.action_head.state_dict().items()}
        atomic_write_bytes(path, save(state, metadata={"format": "pt"}))
        return Path(path)

    def load_head_weights(self, path: str | Path) -> None:
        """Strictly load head weights (keys relative to the head, or prefixed ``action_head.``)."""
        if not Path(path).is_file():
            raise BackboneError(f"head weights file {path} does not exist")
        state = {k.removeprefix(HEAD_WEIGHTS_PREFIX): v for k, v in load_safetensors(path).items()}
        load_state_dict_strictly(self.action_head, state, source=str(path))

    @classmethod
    def from_qwen(
        cls,
        folder: str | Path,
        preset: str,
        head_weights: str | Path | None = None,
        **overrides: Any,
    ) -> StarVLA:
        """The VLM from a local transformers Qwen-VL folder (``config.json``, safetensors, tokenizer
        files), loaded with ``from_pretrained`` and checked strictly; the head from ``head_weights``
        (safetensors) or freshly initialised. The preset gives the head and the data shapes; the
        folder gives the VLM architecture, its tokenizer and image statistics."""
        root = _folder(folder)
        config = _starvla_config(preset, overrides)
        version = _qwen_version(config.qwen_version)
        _check_model_type(root, version, config.qwen_version)
        _, model_class = version.classes()
        vlm, info = model_class.from_pretrained(
            str(root),
            dtype=torch.float32,
            attn_implementation=config.attn_implementation,
            output_loading_info=True,
        )
        problems = [
            f"{len(v)} {k.replace('_', ' ')}, e.g. {sorted(map(str, v))[:3]}"
            for k in ("missing_keys", "unexpected_keys", "mismatched_keys", "error_msgs")
            if (v := info.get(k))
        ]
        if problems:
            raise BackboneError(
                f"{root} does not hold a complete {version.model_class}: " + "; ".join(problems)
            )
        config.qwen = _architecture(vlm.config)
        _read_image_statistics(root, config)
        # Lightning checkpoints hold no tokenizer files: they reload it from here when first needed.
        config.tokenizer = str(root)
        model = cls(config, vlm=vlm, tokenizer=_load_tokenizer(str(root)))
        if head_weights is not None:
            model.load_head_weights(head_weights)
        return model


@dataclass
class VLMEncoding:
    input_ids: Tensor
    """(B, S) token ids (left padded)."""
    head_input: HeadInput
    requested: dict[int, Tensor]
    """Requested layer index -> (B, S, H), contract semantics (pre-norm)."""
    normed_last: Tensor
    """(B, S, H) the last layer after the final norm (what the LM head reads)."""


# -- helpers -------------------------------------------------------------------------------------


def _state(batch: Batch) -> Tensor:
    if "proprio" not in batch:
        raise BackboneError(
            "state_mode needs `proprio` in the batch; set state_mode='none' for data "
            "without proprioception"
        )
    return batch["proprio"]


def _qwen_version(name: str) -> QwenVersion:
    if name not in QWEN_VERSIONS:
        raise BackboneError(f"unknown qwen_version {name!r}; use one of {sorted(QWEN_VERSIONS)}")
    return QWEN_VERSIONS[name]


def _starvla_config(preset: str, overrides: Mapping[str, Any]) -> StarVLAConfig:
    config = preset_config(preset, **overrides)
    if not isinstance(config, StarVLAConfig):
        raise BackboneError(f"preset {preset!r} is not a StarVLA preset (starvla-*)")
    head_class(config.head)  # unknown heads fail before any weights are read
    return config


def _folder(folder: str | Path) -> Path:
    root = Path(folder)
    if not (root / "config.json").is_file():
        raise BackboneError(
            f"{root} is not a local transformers model folder (no config.json); download the "
            "checkpoint where the network allows and pass the folder"
        )
    return root


def _check_model_type(root: Path, version: QwenVersion, name: str) -> None:
    model_type = json.loads((root / "config.json").read_text()).get("model_type")
    if model_type != version.model_type:
        other = [k for k, v in QWEN_VERSIONS.items() if v.model_type == model_type]
        hint = f"; pass qwen_version={other[0]!r} or a matching preset" if other else ""
        raise BackboneError(
            f"{root} holds a {model_type!r} model but qwen_version is {name!r} "
            f"(expects {version.model_type!r}){hint}"
        )


_NOT_ARCHITECTURE = {
    "transformers_version", "architectures", "dtype", "torch_dtype", "_name_or_path",
    "model_type", "image_token_id", "video_token_id", "vision_start_token_id",
    "vision_end_token_id",
}  # fmt: skip


def _architecture(hf_config: Any) -> dict[str, Any]:
    """transformers config -> ``StarVLAConfig.qwen`` (architecture only; ids come from the tokenizer)."""
    raw = hf_config.to_dict()
    out = {k: v for k, v in raw.items() if k not in _NOT_ARCHITECTURE and not k.startswith("_")}
    for sub in ("text_config", "vision_config"):
        out[sub] = {
            k: v
            for k, v in raw[sub].items()
            if k not in _NOT_ARCHITECTURE and not k.startswith("_")
        }
    return json.loads(json.dumps(out))


def _read_image_statistics(root: Path, config: StarVLAConfig) -> None:
    path = root / "preprocessor_config.json"
    if path.is_file():
        pre = json.loads(path.read_text())
        config.image_mean = tuple(pre.get("image_mean", config.image_mean))
        config.image_std = tuple(pre.get("image_std", config.image_std))


def _resize_8bit(images: Tensor, size: int) -> Tensor:
    """(N, 3, H, W) in [0, 1] -> (N, 3, size, size), resized as the Qwen processor StarVLA runs
    (``Qwen2VLImageProcessorFast``, what Qwen3-VL ships): torchvision's bicubic antialiased resize
    of the 8-bit image, which on CPU is torch's fixed-point uint8 kernel (bit-exact here), giving
    an 8-bit image again. Elsewhere the float kernel, clamped and rounded to 8 bits, stands in
    for it (within one grey level)."""
    pixels = (images * 255).round().clamp(0, 255)
    if images.device.type == "cpu":
        resized = F.interpolate(
            pixels.to(torch.uint8), size=(size, size), mode="bicubic", antialias=True
        )
        return resized.float() / 255
    resized = F.interpolate(
        pixels, size=(size, size), mode="bicubic", align_corners=False, antialias=True
    )
    return resized.clamp(0, 255).round() / 255


def _tied(model: StarVLA) -> bool:
    vlm = model.vlm
    return vlm.lm_head.weight is vlm.get_input_embeddings().weight


def _drop_tied_lm_head(
    module: StarVLA, state_dict: dict[str, Any], prefix: str, _metadata: Any
) -> None:
    if _tied(module):
        state_dict.pop(prefix + "vlm.lm_head.weight", None)


def _restore_tied_lm_head(
    module: StarVLA, state_dict: dict[str, Any], prefix: str, *_args: Any
) -> None:
    embed = prefix + "vlm.model.language_model.embed_tokens.weight"
    head = prefix + "vlm.lm_head.weight"
    if _tied(module) and head not in state_dict and embed in state_dict:
        state_dict[head] = state_dict[embed]


__all__ = [
    "HEAD_WEIGHTS_PREFIX",
    "IMAGE_PAD",
    "QWEN_CHAT_TEMPLATE",
    "QWEN_SPECIAL_TOKENS",
    "VIDEO_PAD",
    "VISION_END",
    "VISION_START",
    "StarVLA",
    "TokenIds",
    "VLMEncoding",
    "tiny_qwen_tokenizer",
]
