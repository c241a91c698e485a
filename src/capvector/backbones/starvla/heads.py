"""Action heads for the StarVLA-style backbone: one interface, a registry, three heads.

A head never sees the VLM itself, only a ``HeadInput`` (the VLM's hidden states, their padding mask
and the positions of action query tokens), so every head works with every Qwen-VL wrapper. Each head
is a registered ``ActionHead`` subclass with its own config dataclass; the backbone config selects one
by name (``head``) and passes its fields (``head_args``), so no head carries another head's settings.

Heads, following starVLA/starVLA (``starVLA/model/modules/action_model/``):

- ``oft``: OFT-style parallel decoding. N query tokens in the prompt, their last-layer states through
  an MLP-ResNet, L1 loss (``MLP_ActionHeader.py``, framework ``VLM4A/QwenOFT.py``).
- ``gr00t``: GR00T-N1.5-style DiT flow matching, cross-attending to the last VLM layer
  (``GR00T_ActionHeader.py``, ``flow_matching_head/cross_attention_dit.py``, ``VLM4A/QwenGR00T.py``).
- ``layerwise``: PI_v3-style layer-wise flow matching. Per-layer projectors to a narrow width, DiT
  block i cross-attends to VLM layer i (``LayerwiseFM_ActionHeader.py``, ``VLM4A/QwenPI_v3.py``).

Parameter names match StarVLA's, so its checkpoints load through a prefix map (``convert.py``).
StarVLA duplicates ``ActionEncoder``/``MLP``/the DiT between its two flow heads; here they are shared.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from capvector.backbones.base import BackboneError, draw_flow_noise
from capvector.backbones.common import MLPResNet
from capvector.registry import Registry

# -- the interface -------------------------------------------------------------------------------


@dataclass
class HeadInput:
    """What a head conditions on. B batch, S sequence, H VLM width, L VLM layers, N query tokens."""

    last_hidden: Tensor
    """(B, S, H) the last decoder layer as StarVLA reads it (``hidden_states[-1]``): after the final
    norm for Qwen2.5-VL, before it for Qwen3-VL (``starvla.QwenVersion.head_reads_final_norm``)."""
    mask: Tensor
    """(B, S) bool: True at real (non-padding) tokens."""
    layers: tuple[Tensor, ...] = ()
    """L tensors (B, S, H): HF's ``hidden_states[1:]`` as StarVLA reads them (entry k: the input
    of decoder layer k + 1; the last is ``last_hidden``). Filled only for heads with
    ``uses_all_layers``."""
    query_positions: Tensor | None = None
    """(B, N) sequence positions of the action query tokens, for heads with query tokens."""

    def to(self, dtype: torch.dtype) -> HeadInput:
        return HeadInput(
            last_hidden=self.last_hidden.to(dtype),
            mask=self.mask,
            layers=tuple(layer.to(dtype) for layer in self.layers),
            query_positions=self.query_positions,
        )


@dataclass(frozen=True)
class HeadDims:
    """Shapes a head is built for; the backbone derives them from its VLM and config."""

    vlm_width: int
    vlm_layers: int
    action_dim: int
    chunk_size: int
    state_dim: int = 0
    """P of the state token fed to the head; 0 when the state is absent or written into the prompt."""


class ActionHead(nn.Module, ABC):
    """Base class of the heads: ``loss(cond, actions, state)`` for training, ``sample(cond, state)``.

    ``actions`` are (B, T, A) in normalised space, ``state`` is (B, P) or None.
    """

    name: ClassVar[str] = ""
    config_class: ClassVar[type] = object
    uses_all_layers: ClassVar[bool] = False
    """Whether ``HeadInput.layers`` must hold every VLM layer (else only the last is computed)."""
    accepts_state: ClassVar[bool] = False
    """Whether the head can take the state as an input token (``state_mode='head'``)."""
    loss_predicts_actions: ClassVar[bool] = False
    """Whether the training loss computes the predicted actions anyway (an L1 head), so returning
    them costs nothing; a flow head's loss does not, and predicting would mean sampling."""

    def __init__(self, config: Any, dims: HeadDims) -> None:
        super().__init__()
        self.config = config
        self.dims = dims
        if dims.state_dim and not self.accepts_state:
            raise BackboneError(
                f"the {self.name!r} head has no state input; use state_mode='prompt' (the state as "
                "256-bin text, as StarVLA's QwenOFT) or 'none'"
            )

    @property
    def num_query_tokens(self) -> int:
        """N action query tokens the prompt must carry (0: the head reads the whole sequence)."""
        return 0

    @property
    def query_token(self) -> str:
        """The added special token used as action query (only for heads with query tokens)."""
        return ""

    @property
    def bidirectional_queries(self) -> bool:
        """Whether the query tokens attend to each other in both directions inside the VLM."""
        return False

    def prompt_suffix(self) -> str:
        """Text appended to the instruction (e.g. the query tokens); empty for most heads."""
        return ""

    @abstractmethod
    def loss(
        self,
        cond: HeadInput,
        actions: Tensor,
        state: Tensor | None = None,
        noise_seeds: Tensor | None = None,
    ) -> Tensor:
        """Scalar training loss for target ``actions`` (B, T, A). Heads that draw noise draw
        sample b's from ``noise_seeds[b]`` (``batch["noise_seed"]``), else from the global RNG."""

    @abstractmethod
    def sample(self, cond: HeadInput, state: Tensor | None = None) -> Tensor:
        """(B, T, A) predicted actions."""

    def loss_and_actions(
        self,
        cond: HeadInput,
        actions: Tensor,
        state: Tensor | None = None,
        noise_seeds: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Loss and predictions from one call; heads whose loss already predicts override this."""
        loss = self.loss(cond, actions, state, noise_seeds)
        with torch.no_grad():
            predicted = self.sample(cond, state)
        return loss, predicted

    def config_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self.config)


# -- registry ------------------------------------------------------------------------------------

ACTION_HEADS: Registry[type[ActionHead]] = Registry(
    "action head", base=ActionHead, error=BackboneError
)
"""The heads a config's ``head`` names: a registered name, or ``module:Class`` for a head defined
in another package."""
H = TypeVar("H", bound=type[ActionHead])


def register_head(name: str) -> Callable[[H], H]:
    """Class decorator: makes a head buildable by name from a backbone config's ``head`` field."""

    def decorate(cls: H) -> H:
        cls.name = name
        return ACTION_HEADS.register(name)(cls)

    return decorate


def head_names() -> list[str]:
    return ACTION_HEADS.names()


def head_class(name: str) -> type[ActionHead]:
    return ACTION_HEADS.get(name)


def build_head(name: str, args: Mapping[str, Any], dims: HeadDims) -> ActionHead:
    """The head ``name`` with config fields ``args`` (unknown fields are an error, not ignored)."""
    cls = head_class(name)
    known = {f.name for f in dataclasses.fields(cls.config_class)}
    unknown = sorted(set(args) - known)
    if unknown:
        raise BackboneError(
            f"head_args {unknown} are not fields of the {name!r} head ({cls.config_class.__name__}); "
            f"valid fields: {sorted(known)}"
        )
    return cls(cls.config_class(**args), dims)


# -- OFT: query tokens -> MLP-ResNet -> L1 -------------------------------------------------------


@dataclass
class OFTHeadConfig:
    num_blocks: int = 2
    """Residual blocks of the MLP-ResNet (2 in StarVLA's ``L1RegressionActionHead``)."""
    hidden_multiplier: int = 2
    """MLP-ResNet width = multiplier x VLM width (StarVLA: ``hidden_dim=action_hidden_dim * 2``)."""
    bidirectional_queries: bool = False
    """Let the query tokens attend to each other in both directions, as OpenVLA-OFT's action slots
    do. StarVLA keeps Qwen's causal mask (query i sees only queries < i)."""
    query_token: str = "<|action_query|>"
    """A special token added to the tokenizer, so it is always exactly one token. StarVLA uses the
    emoji "🔍", which the Qwen3.5 tokenizer splits into 3 tokens (starVLA issue #291)."""
    prompt_suffix: str = (
        " Please predict the next {chunk} robot actions: <action>{queries}<action>."
    )
    """Appended to the instruction; ``{queries}`` becomes T query tokens (StarVLA's QwenOFT text)."""


@register_head("oft")
class OFTHead(ActionHead):
    """Each of the T query tokens' last-layer state -> MLP-ResNet -> one action (B, T, A)."""

    config_class = OFTHeadConfig
    loss_predicts_actions = True

    def __init__(self, config: OFTHeadConfig, dims: HeadDims) -> None:
        super().__init__(config, dims)
        if "{queries}" not in config.prompt_suffix:
            raise BackboneError(
                f"oft prompt_suffix {config.prompt_suffix!r} has no '{{queries}}' placeholder for "
                "the action query tokens"
            )
        width = dims.vlm_width
        self.model = MLPResNet(
            config.num_blocks, width, config.hidden_multiplier * width, dims.action_dim
        )

    @property
    def num_query_tokens(self) -> int:
        return self.dims.chunk_size

    @property
    def query_token(self) -> str:
        return self.config.query_token

    @property
    def bidirectional_queries(self) -> bool:
        return self.config.bidirectional_queries

    def prompt_suffix(self) -> str:
        queries = self.config.query_token * self.dims.chunk_size
        return self.config.prompt_suffix.replace("{chunk}", str(self.dims.chunk_size)).replace(
            "{queries}", queries
        )

    def sample(self, cond: HeadInput, state: Tensor | None = None) -> Tensor:
        if cond.query_positions is None:
            raise BackboneError("the oft head needs query_positions in its HeadInput")
        index = cond.query_positions.unsqueeze(-1).expand(-1, -1, cond.last_hidden.shape[-1])
        return self.model(torch.gather(cond.last_hidden, 1, index))

    def loss(
        self,
        cond: HeadInput,
        actions: Tensor,
        state: Tensor | None = None,
        noise_seeds: Tensor | None = None,
    ) -> Tensor:
        return F.l1_loss(self.sample(cond, state), actions)

    def loss_and_actions(
        self,
        cond: HeadInput,
        actions: Tensor,
        state: Tensor | None = None,
        noise_seeds: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        predicted = self.sample(cond, state)
        return F.l1_loss(predicted, actions), predicted


# -- DiT building blocks (GR00T N1.5's cross-attention DiT, parameter names kept) ----------------


def _timestep_sinusoid(timestep: Tensor, dim: int = 256) -> Tensor:
    """diffusers' ``Timesteps(dim, flip_sin_to_cos=True, downscale_freq_shift=1)``: [cos, sin]."""
    half = dim // 2
    exponent = -math.log(10000.0) * torch.arange(half, device=timestep.device) / (half - 1)
    angles = timestep.float()[:, None] * exponent.exp()[None, :]
    return torch.cat([angles.cos(), angles.sin()], dim=-1)


def _action_sinusoid(timestep: Tensor, dim: int) -> Tensor:
    """GR00T's ``SinusoidalPositionalEncoding`` of a (B, T) timestep grid: [sin, cos], (B, T, dim)."""
    half = dim // 2
    exponent = -torch.arange(half, device=timestep.device) * (math.log(10000.0) / half)
    angles = timestep.float().unsqueeze(-1) * exponent.exp()
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class _TimestepMLP(nn.Module):
    """diffusers' ``TimestepEmbedding``: linear_1 -> SiLU -> linear_2."""

    def __init__(self, in_dim: int, width: int) -> None:
        super().__init__()
        self.linear_1 = nn.Linear(in_dim, width)
        self.linear_2 = nn.Linear(width, width)

    def forward(self, x: Tensor) -> Tensor:
        return self.linear_2(F.silu(self.linear_1(x)))


class TimestepEncoder(nn.Module):
    """Discrete flow timestep (0..buckets-1) -> (B, width) conditioning for AdaLN."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.timestep_embedder = _TimestepMLP(256, width)

    def forward(self, timestep: Tensor) -> Tensor:
        proj = _timestep_sinusoid(timestep).to(self.timestep_embedder.linear_1.weight.dtype)
        return self.timestep_embedder(proj)


class AdaLayerNorm(nn.Module):
    """LayerNorm without affine parameters, scaled and shifted by the timestep embedding."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.linear = nn.Linear(width, 2 * width)
        self.norm = nn.LayerNorm(width, eps=1e-5, elementwise_affine=False)

    def forward(self, x: Tensor, temb: Tensor) -> Tensor:
        scale, shift = self.linear(F.silu(temb)).chunk(2, dim=1)
        return self.norm(x) * (1 + scale[:, None]) + shift[:, None]


class Attention(nn.Module):
    """Multi-head attention with diffusers' parameter names (to_q/to_k/to_v/to_out.0).

    When ``context`` has fewer rows than ``x`` (the flow loss repeats the action batch k times over
    one VLM pass), keys and values are projected once and tiled: the repeated noise samples share
    them, as the VLM features are shared in StarVLA's repetition (``QwenGR00T.forward``).
    """

    def __init__(self, width: int, num_heads: int, kv_dim: int | None, dropout: float) -> None:
        super().__init__()
        if width % num_heads:
            raise BackboneError(f"DiT width {width} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.to_q = nn.Linear(width, width)
        self.to_k = nn.Linear(kv_dim or width, width)
        self.to_v = nn.Linear(kv_dim or width, width)
        self.to_out = nn.ModuleList([nn.Linear(width, width), nn.Dropout(dropout)])

    def forward(
        self, x: Tensor, context: Tensor | None = None, context_mask: Tensor | None = None
    ) -> Tensor:
        context = x if context is None else context
        batch, length, width = x.shape
        q = self.to_q(x)
        k, v = self.to_k(context), self.to_v(context)
        if k.shape[0] != batch:
            if batch % k.shape[0]:
                raise BackboneError(f"{batch} queries do not tile {k.shape[0]} context rows")
            repeats = batch // k.shape[0]
            k, v = k.repeat(repeats, 1, 1), v.repeat(repeats, 1, 1)
            if context_mask is not None:
                context_mask = context_mask.repeat(repeats, 1)

        def heads(t: Tensor) -> Tensor:
            return t.reshape(batch, -1, self.num_heads, width // self.num_heads).transpose(1, 2)

        mask = None if context_mask is None else context_mask[:, None, None, :]
        out = F.scaled_dot_product_attention(heads(q), heads(k), heads(v), attn_mask=mask)
        out = out.transpose(1, 2).reshape(batch, length, width)
        return self.to_out[1](self.to_out[0](out))


class _GELUProj(nn.Module):
    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.proj = nn.Linear(in_dim, out_dim)

    def forward(self, x: Tensor) -> Tensor:
        return F.gelu(self.proj(x), approximate="tanh")


class FeedForward(nn.Module):
    """diffusers' ``FeedForward(activation_fn='gelu-approximate', final_dropout=True)``."""

    def __init__(self, width: int, dropout: float) -> None:
        super().__init__()
        self.net = nn.ModuleList(
            [
                _GELUProj(width, 4 * width),
                nn.Dropout(dropout),
                nn.Linear(4 * width, width),
                nn.Dropout(dropout),
            ]
        )

    def forward(self, x: Tensor) -> Tensor:
        for layer in self.net:
            x = layer(x)
        return x


class DiTBlock(nn.Module):
    """AdaLN -> (cross- or self-) attention -> residual; LayerNorm -> GELU MLP -> residual."""

    def __init__(self, width: int, num_heads: int, kv_dim: int | None, dropout: float) -> None:
        super().__init__()
        self.norm1 = AdaLayerNorm(width)
        self.attn1 = Attention(width, num_heads, kv_dim, dropout)
        self.final_dropout = nn.Dropout(dropout)
        self.norm3 = nn.LayerNorm(width, eps=1e-5, elementwise_affine=False)
        self.ff = FeedForward(width, dropout)

    def forward(
        self,
        x: Tensor,
        temb: Tensor,
        context: Tensor | None = None,
        context_mask: Tensor | None = None,
    ) -> Tensor:
        x = x + self.final_dropout(self.attn1(self.norm1(x, temb), context, context_mask))
        return x + self.ff(self.norm3(x))


class _DiTBlocks(nn.Module):
    """What both DiTs are: a timestep encoder and ``num_layers`` DiT blocks, block i cross-attending
    to context i; odd blocks self-attend instead when interleaved (``cross_attention_dit.DiT``)."""

    def __init__(
        self,
        width: int,
        num_heads: int,
        num_layers: int,
        context_dim: int,
        dropout: float,
        interleave_self_attention: bool,
    ) -> None:
        super().__init__()
        self.self_attention_blocks = {
            i for i in range(num_layers) if interleave_self_attention and i % 2 == 1
        }
        self.timestep_encoder = TimestepEncoder(width)
        self.transformer_blocks = nn.ModuleList(
            DiTBlock(
                width, num_heads, None if i in self.self_attention_blocks else context_dim, dropout
            )
            for i in range(num_layers)
        )

    def run_blocks(
        self, x: Tensor, contexts: Sequence[Tensor], context_mask: Tensor, timestep: Tensor
    ) -> tuple[Tensor, Tensor]:
        """The blocks' output and the timestep embedding (B, width) they were conditioned on."""
        temb = self.timestep_encoder(timestep)
        for i, (block, context) in enumerate(zip(self.transformer_blocks, contexts, strict=True)):
            if i in self.self_attention_blocks:
                x = block(x, temb)
            else:
                x = block(x, temb, context, context_mask)
        return x, temb


class CrossAttentionDiT(_DiTBlocks):
    """GR00T's DiT: blocks cross-attend to the VLM tokens (odd blocks self-attend when interleaved),
    then an AdaLN-modulated output projection."""

    def __init__(
        self,
        width: int,
        num_heads: int,
        num_layers: int,
        cross_dim: int,
        output_dim: int,
        dropout: float,
        interleave_self_attention: bool,
    ) -> None:
        super().__init__(
            width, num_heads, num_layers, cross_dim, dropout, interleave_self_attention
        )
        self.norm_out = nn.LayerNorm(width, eps=1e-6, elementwise_affine=False)
        self.proj_out_1 = nn.Linear(width, 2 * width)
        self.proj_out_2 = nn.Linear(width, output_dim)

    def forward(self, x: Tensor, context: Tensor, context_mask: Tensor, timestep: Tensor) -> Tensor:
        contexts = [context] * len(self.transformer_blocks)
        x, temb = self.run_blocks(x, contexts, context_mask, timestep)
        shift, scale = self.proj_out_1(F.silu(temb)).chunk(2, dim=1)
        return self.proj_out_2(self.norm_out(x) * (1 + scale[:, None]) + shift[:, None])


class LayerwiseDiT(_DiTBlocks):
    """PI_v3's layer-wise DiT: block i cross-attends to (projected) VLM layer i. As StarVLA's
    ``LayerwiseFlowmatchingActionHead`` (``DiT.forward(..., return_pre_output=True)``), the output
    goes to the decoder without a final projection.

    ``interleave_self_attention``: odd blocks self-attend and ignore their VLM layer, as
    ``cross_attention_dit.DiT.forward``. The parameter shapes are the same either way (the context
    is pre-projected to the DiT width), so only the config tells the two checkpoints apart."""

    def __init__(
        self,
        width: int,
        num_heads: int,
        num_layers: int,
        dropout: float,
        interleave_self_attention: bool = False,
    ) -> None:
        super().__init__(width, num_heads, num_layers, width, dropout, interleave_self_attention)

    def forward(
        self, x: Tensor, contexts: list[Tensor], context_mask: Tensor, timestep: Tensor
    ) -> Tensor:
        return self.run_blocks(x, contexts, context_mask, timestep)[0]


class MLP(nn.Module):
    """Linear -> ReLU -> Linear (GR00T's state encoder and action decoder)."""

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int) -> None:
        super().__init__()
        self.layer1 = nn.Linear(in_dim, hidden_dim)
        self.layer2 = nn.Linear(hidden_dim, out_dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.layer2(F.relu(self.layer1(x)))


class ActionEncoder(nn.Module):
    """Noisy action + flow timestep -> token: W1 a, concat sinusoid(t), W2, swish, W3 (GR00T)."""

    def __init__(self, action_dim: int, width: int) -> None:
        super().__init__()
        self.width = width
        self.layer1 = nn.Linear(action_dim, width)
        self.layer2 = nn.Linear(2 * width, width)
        self.layer3 = nn.Linear(width, width)

    def forward(self, actions: Tensor, timestep: Tensor) -> Tensor:
        """(B, T, A), (B,) -> (B, T, width)."""
        a = self.layer1(actions)
        tau = _action_sinusoid(timestep[:, None].expand(-1, actions.shape[1]), self.width)
        return self.layer3(F.silu(self.layer2(torch.cat([a, tau.to(a.dtype)], dim=-1))))


# -- flow matching, shared by the two DiT heads ---------------------------------------------------


@dataclass
class FlowHeadConfig:
    """Flow-matching settings shared by the DiT heads (GR00T N1.5 convention, as StarVLA)."""

    width: int = 768
    num_heads: int = 12
    hidden_size: int = 1024
    """Hidden width of the state encoder and the action decoder MLPs."""
    dropout: float = 0.2
    num_future_tokens: int = 32
    """Learned tokens between the state token and the action tokens (GR00T's misnamed
    ``num_target_vision_tokens``)."""
    max_seq_len: int = 1024
    """Rows of the learned action position embedding (the first T are used)."""
    noise_beta_alpha: float = 1.5
    noise_beta_beta: float = 1.0
    noise_s: float = 0.999
    """t = (s - u) / s, u ~ Beta(alpha, beta): more weight on noisy t (GR00T's ``sample_time``;
    the GR00T head clips u at s first, the layerwise head does not, as upstream)."""
    num_timestep_buckets: int = 1000
    num_inference_steps: int = 4
    """Euler steps from noise (t=0) to actions (t=1)."""
    repeated_diffusion_steps: int = 8
    """Training copies of the action batch per VLM pass, each with fresh noise and t (CogACT's
    trick): the VLM cost is paid once for k flow samples."""


class FlowMatchingHead(ActionHead):
    """Flow matching over the action chunk: x_t = (1 - t) * noise + t * actions, the network
    predicts the velocity actions - noise (MSE); sampling integrates it with Euler steps.

    The DiT input sequence is [state token (optional), future tokens, action tokens] and the last
    T outputs are decoded to velocities, as GR00T's ``FlowmatchingActionHead``.
    """

    accepts_state = True
    config: FlowHeadConfig
    clip_time_draw: ClassVar[bool] = True
    """Clip u at s before t = (s - u) / s (``GR00T_ActionHeader.sample_time``); StarVLA's
    ``LayerwiseFM_ActionHeader.sample_time`` does not clip, so its t can dip to (s - 1) / s < 0."""

    def __init__(self, config: FlowHeadConfig, dims: HeadDims, decoder_in: int) -> None:
        super().__init__(config, dims)
        if dims.chunk_size > config.max_seq_len:
            raise BackboneError(
                f"chunk_size {dims.chunk_size} exceeds the head's max_seq_len {config.max_seq_len}"
            )
        for name in ("num_inference_steps", "repeated_diffusion_steps", "num_timestep_buckets"):
            if getattr(config, name) < 1:
                raise BackboneError(f"head_args {name} must be at least 1")
        width = config.width
        self.state_encoder = (
            MLP(dims.state_dim, config.hidden_size, width) if dims.state_dim else None
        )
        self.action_encoder = ActionEncoder(dims.action_dim, width)
        self.action_decoder = MLP(decoder_in, config.hidden_size, dims.action_dim)
        self.future_tokens = nn.Embedding(config.num_future_tokens, width)
        self.position_embedding = nn.Embedding(config.max_seq_len, width)
        nn.init.normal_(self.future_tokens.weight, std=0.02)
        nn.init.normal_(self.position_embedding.weight, std=0.02)
        self._beta: torch.distributions.Beta | None = None

    @abstractmethod
    def prepare(self, cond: HeadInput) -> tuple[Any, Tensor]:
        """VLM features the DiT attends to, computed once per VLM pass, and their (B, S) mask."""

    @abstractmethod
    def denoiser(self, tokens: Tensor, context: Any, mask: Tensor, timestep: Tensor) -> Tensor:
        """The DiT over the (B', 1? + F + T, width) token sequence."""

    def velocity(
        self, context: Any, mask: Tensor, noisy: Tensor, timestep: Tensor, state: Tensor | None
    ) -> Tensor:
        """Predicted velocity (B', T, A) for noisy actions (B', T, A) at discrete ``timestep``."""
        actions = self.action_encoder(noisy, timestep)
        positions = torch.arange(actions.shape[1], device=actions.device)
        tokens = [
            self.future_tokens.weight.unsqueeze(0).expand(actions.shape[0], -1, -1),
            actions + self.position_embedding(positions).unsqueeze(0),
        ]
        if self.state_encoder is not None:
            if state is None:
                raise BackboneError("this head was built with a state token but got no state")
            tokens.insert(0, self.state_encoder(state.to(actions.dtype)).unsqueeze(1))
        out = self.denoiser(torch.cat(tokens, dim=1), context, mask, timestep)
        return self.action_decoder(out[:, -noisy.shape[1] :])

    def sample_time(self, n: int, device: torch.device) -> Tensor:
        if self._beta is None:
            c = self.config
            self._beta = torch.distributions.Beta(
                torch.tensor(c.noise_beta_alpha), torch.tensor(c.noise_beta_beta)
            )
        u = self._beta.sample((n,)).to(device)
        s = self.config.noise_s
        if self.clip_time_draw:
            u = u.clamp(max=s)
        # Upstream's formula, (s - u) / s, not the algebraically equal s * (1 - u) / s rewritten:
        # the same float operations give the same bits, so recorded draws replay exactly.
        return (s - u) / s

    def loss(
        self,
        cond: HeadInput,
        actions: Tensor,
        state: Tensor | None = None,
        noise_seeds: Tensor | None = None,
    ) -> Tensor:
        k = self.config.repeated_diffusion_steps
        repeated = actions.repeat(k, 1, 1)
        noise, t = draw_flow_noise(repeated, self.sample_time, noise_seeds)
        return self.flow_loss(cond, actions, state, noise, t)

    def flow_loss(
        self, cond: HeadInput, actions: Tensor, state: Tensor | None, noise: Tensor, t: Tensor
    ) -> Tensor:
        """The loss for given draws: ``noise`` (k·B, T, A) and times ``t`` (k·B,), the k copies of
        the batch laid out as ``actions.repeat(k, 1, 1)`` (StarVLA's ``repeated_diffusion_steps``
        over one VLM pass, ``QwenGR00T.forward``)."""
        context, mask = self.prepare(cond)
        k = self.config.repeated_diffusion_steps
        actions = actions.repeat(k, 1, 1)
        state = None if state is None else state.repeat(k, 1)
        t = t.to(actions.dtype)[:, None, None]
        noisy = (1 - t) * noise + t * actions
        timestep = (t[:, 0, 0] * self.config.num_timestep_buckets).long()
        predicted = self.velocity(context, mask, noisy, timestep, state)
        return F.mse_loss(predicted, actions - noise)

    def sample(
        self, cond: HeadInput, state: Tensor | None = None, noise: Tensor | None = None
    ) -> Tensor:
        """Euler integration from ``noise`` (B, T, A; drawn from the global RNG when None) at
        t = 0, 1/n, ... (``FlowmatchingActionHead.predict_action``)."""
        context, mask = self.prepare(cond)
        batch = mask.shape[0]
        dtype = self.action_encoder.layer1.weight.dtype
        x = noise
        if x is None:
            x = torch.randn(
                batch, self.dims.chunk_size, self.dims.action_dim, device=mask.device, dtype=dtype
            )
        steps = self.config.num_inference_steps
        dt = 1.0 / steps
        for i in range(steps):
            bucket = int(i / float(steps) * self.config.num_timestep_buckets)
            timestep = torch.full((batch,), bucket, device=mask.device, dtype=torch.long)
            x = x + dt * self.velocity(context, mask, x, timestep, state)
        return x


@dataclass
class GR00THeadConfig(FlowHeadConfig):
    """DiT-B (768 wide, 12 heads x 64) with 16 blocks, StarVLA's QwenGR00T default."""

    num_layers: int = 16
    interleave_self_attention: bool = True
    """Even blocks cross-attend to the VLM tokens, odd blocks self-attend."""


@register_head("gr00t")
class GR00THead(FlowMatchingHead):
    """DiT flow matching cross-attending to the last VLM layer (all image and text tokens)."""

    config_class = GR00THeadConfig
    config: GR00THeadConfig

    def __init__(self, config: GR00THeadConfig, dims: HeadDims) -> None:
        super().__init__(config, dims, decoder_in=config.hidden_size)
        self.model = CrossAttentionDiT(
            width=config.width,
            num_heads=config.num_heads,
            num_layers=config.num_layers,
            cross_dim=dims.vlm_width,
            output_dim=config.hidden_size,
            dropout=config.dropout,
            interleave_self_attention=config.interleave_self_attention,
        )

    def prepare(self, cond: HeadInput) -> tuple[Tensor, Tensor]:
        # The VLM padding is masked, as QwenGR00T passes ``encoder_attention_mask`` (older StarVLA
        # versions passed none and attended to the padding of shorter prompts).
        return cond.last_hidden, cond.mask

    def denoiser(self, tokens: Tensor, context: Tensor, mask: Tensor, timestep: Tensor) -> Tensor:
        return self.model(tokens, context, mask, timestep)


@dataclass
class LayerwiseHeadConfig(FlowHeadConfig):
    """PI_v3: a 1024-wide DiT (16 heads x 64) with one block per VLM layer."""

    width: int = 1024
    num_heads: int = 16
    repeated_diffusion_steps: int = 2
    """QwenPI_v3 reads ``trainer.repeated_diffusion_steps`` (16 when absent; its framework default
    ``action_model.repeated_diffusion_steps: 2`` is never read); our preset keeps 2 for memory and
    the importer sets the run's value."""
    interleave_self_attention: bool = False
    """Odd DiT blocks self-attend instead of cross-attending to their VLM layer (PI_v3's
    ``diffusion_model_cfg.interleave_self_attention``, alias ``use_canonical_forward``)."""


@register_head("layerwise")
class LayerwiseHead(FlowMatchingHead):
    """Per-layer projectors (LayerNorm + Linear, VLM width -> ``width``); DiT block i cross-attends
    to projected VLM layer i. StarVLA's full-width QwenPI (a head as large as the VLM) is not built:
    the width must be narrower than the VLM."""

    config_class = LayerwiseHeadConfig
    uses_all_layers = True
    config: LayerwiseHeadConfig
    clip_time_draw = False  # LayerwiseFM_ActionHeader.sample_time has no clamp

    def __init__(self, config: LayerwiseHeadConfig, dims: HeadDims) -> None:
        if config.width >= dims.vlm_width:
            raise BackboneError(
                f"layerwise head width {config.width} must be narrower than the VLM "
                f"({dims.vlm_width}): at full width the head is as large as the VLM (StarVLA's "
                "QwenPI); use the PI_v3 width (1024 for 2-3k wide VLMs)"
            )
        super().__init__(config, dims, decoder_in=config.width)
        self.projectors = nn.ModuleList(
            nn.Sequential(nn.LayerNorm(dims.vlm_width), nn.Linear(dims.vlm_width, config.width))
            for _ in range(dims.vlm_layers)
        )
        self.model = LayerwiseDiT(
            config.width,
            config.num_heads,
            dims.vlm_layers,
            config.dropout,
            config.interleave_self_attention,
        )

    def prepare(self, cond: HeadInput) -> tuple[list[Tensor], Tensor]:
        if len(cond.layers) != len(self.projectors):
            raise BackboneError(
                f"the layerwise head needs {len(self.projectors)} VLM layers, got {len(cond.layers)}"
            )
        # Projected once per VLM pass (QwenPI_v3._encode_vl_hidden_states), padding masked as
        # QwenPI_v3 passes its ``encoder_attention_mask``.
        return [proj(h) for proj, h in zip(self.projectors, cond.layers, strict=True)], cond.mask

    def denoiser(
        self, tokens: Tensor, context: list[Tensor], mask: Tensor, timestep: Tensor
    ) -> Tensor:
        return self.model(tokens, context, mask, timestep)


__all__ = [
    "ACTION_HEADS",
    "ActionHead",
    "FlowHeadConfig",
    "FlowMatchingHead",
    "GR00THead",
    "GR00THeadConfig",
    "HeadDims",
    "HeadInput",
    "LayerwiseHead",
    "LayerwiseHeadConfig",
    "OFTHead",
    "OFTHeadConfig",
    "build_head",
    "head_class",
    "head_names",
    "register_head",
]
