"""Multimodal-reasoning co-training (StarVLA's VLM co-training, ``train_starvla_cotrain.py``).

A next-token loss on text answers about the scene — the per-step annotations the demos carry (what
the robot is doing, where things are) — through the backbone's own language head in a separate,
causal pass, so the action pathway's bidirectional attention is untouched. L = L_action + λ·L_text
with λ = 0.1 as StarVLA's ``loss_scale.vlm``. Only answer tokens are scored; prompt, visual and
padding positions carry label -100. ``samples`` caps how many of each batch's samples the text
pass scores: StarVLA's LIBERO configs pair 4 VLM samples with 16 VLA samples per step, and the
text pass over a long answer costs several action passes.

``vocabulary="answers"`` scores each answer token against the tokens the training set's answers
use instead of the whole vocabulary: a softmax over those tokens alone. LIBERO's annotations are
a small grammar of object names, digits and directions: 64 Gemma tokens for the mini study's
LIBERO-Spatial demos. A deviation from StarVLA, whose VLM loss is over all of Qwen's tokens, for
the CPU: Gemma's 262 k-token head is most of the mini's reasoning pass
(``benchmarks/bench_objectives.py``). What it leaves out is the push down on every token no
answer uses, so it holds the hidden states less to the pretrained head's whole vocabulary.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Literal

import torch
import torch.nn.functional as F
from lightning.pytorch.utilities import rank_zero_info
from torch import Tensor
from torch.utils.data import Dataset

from capvector.backbones.base import VLABackbone, VLAOutput
from capvector.data.batch import Batch
from capvector.errors import CapVectorError
from capvector.objectives.base import OBJECTIVES, Objective

DEFAULT_QUESTION = "What is the robot doing, and where are the objects?"


@OBJECTIVES.register("reasoning")
class ReasoningCoTraining(Objective):
    def __init__(
        self,
        weight: float = 0.1,
        question: str = DEFAULT_QUESTION,
        prompt_template: str = "Task: {instruction}. Question: {question}\nAnswer: ",
        name: str = "reasoning",
        samples: int | None = None,
        vocabulary: Literal["full", "answers"] = "full",
    ) -> None:
        """``samples``: score the first ``samples`` of each (shuffled) batch, None for all.
        ``vocabulary``: the softmax over every token (``full``) or over the tokens of the
        training set's answers (``answers``, collected when the fit starts)."""
        super().__init__(name=name, weight=weight)
        if samples is not None and samples < 1:
            raise CapVectorError(
                f"reasoning samples must be at least 1 (or None: all), got {samples}"
            )
        if vocabulary not in ("full", "answers"):
            raise CapVectorError(
                f"reasoning vocabulary must be 'full' or 'answers', got {vocabulary!r}"
            )
        self.question = question
        self.prompt_template = prompt_template
        self.samples = samples
        self.vocabulary = vocabulary
        # sorted token ids (vocabulary="answers"); not saved: rebuilt from the data at every start
        self.register_buffer("answer_vocabulary", None, persistent=False)

    def bind(self, backbone: VLABackbone) -> None:
        # The LM head trains with the text objective, unless the run is LoRA (then only adapters
        # and action heads train, as everywhere else).
        if any(".lora_" in name for name, _ in backbone.named_parameters()):
            return
        head = set(backbone.language_head_parameter_names())
        for name, param in backbone.named_parameters():
            if name in head:
                param.requires_grad_(True)

    def bind_data(self, dataset: Dataset, backbone: VLABackbone) -> None:
        if self.vocabulary == "answers":
            read = getattr(dataset, "annotations", None)
            if read is None:
                raise CapVectorError(
                    "reasoning vocabulary='answers' reads the training set's annotations; "
                    f"{type(dataset).__name__} has none: train on HDF5 demos with "
                    "data.load_annotations=true, or set vocabulary='full'"
                )
            self.answer_vocabulary = answer_vocabulary(read(), backbone)

    def forward(self, batch: Batch, output: VLAOutput, backbone: VLABackbone) -> Tensor:
        # Only the answer positions reach the vocabulary projection (the same loss as scoring
        # every position with label -100 elsewhere, without the (B, S, V) logits).
        if self.vocabulary == "answers" and self.answer_vocabulary is None:
            raise CapVectorError(
                "reasoning vocabulary='answers' is collected from the training set when the fit "
                "starts (AuxiliaryObjective with a data module); call bind_data(dataset, "
                "backbone) first when using the objective by hand"
            )
        logits, labels = backbone.answer_logits(*self.text_inputs(batch), self.answer_vocabulary)
        return F.cross_entropy(logits.float(), labels)

    def text_inputs(self, batch: Batch) -> tuple[Batch, list[str], list[str]]:
        """The scored samples of ``batch``, their prompts and their answers (annotations)."""
        if "annotation" not in batch:
            raise CapVectorError(
                "reasoning co-training needs per-step text annotations: set data.load_annotations=true "
                "(demos from `capvector demos` carry them)"
            )
        if self.samples is not None:  # every entry of a batch is batch-first (tensors, lists)
            batch = {key: value[: self.samples] for key, value in batch.items()}  # type: ignore[assignment]
        prompts = [
            self.prompt_template.format(instruction=instruction, question=self.question)
            for instruction in batch["instruction"]
        ]
        return batch, prompts, list(batch["annotation"])


def answer_vocabulary(answers: Iterable[str], backbone: VLABackbone) -> Tensor:
    """The sorted token ids ``backbone``'s text pass scores for ``answers`` (each distinct answer
    tokenized once)."""
    distinct = set(answers)
    if not distinct:
        raise CapVectorError(
            "the training set has no annotations to build the answer vocabulary of"
        )
    ids = {i for answer in distinct for i in backbone.answer_label_ids(answer)}
    rank_zero_info(
        f"reasoning: an answer vocabulary of {len(ids)} tokens, from {len(distinct)} distinct answers"
    )
    return torch.tensor(sorted(ids), dtype=torch.long)
