"""Multimodal-reasoning co-training (StarVLA's VLM co-training, ``train_starvla_cotrain.py``).

A next-token loss on text answers about the scene — the per-step annotations the demos carry (what
the robot is doing, where things are) — through the backbone's own language head in a separate,
causal pass, so the action pathway's bidirectional attention is untouched. L = L_action + λ·L_text
with λ = 0.1 as StarVLA's ``loss_scale.vlm``. Only answer tokens are scored; prompt, visual and
padding positions carry label -100. ``samples`` caps how many of each batch's samples the text
pass scores: StarVLA's LIBERO configs pair 4 VLM samples with 16 VLA samples per step, and the
text pass over a long answer costs several action passes.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

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
    ) -> None:
        """``samples``: score the first ``samples`` of each (shuffled) batch, None for all."""
        super().__init__(name=name, weight=weight)
        if samples is not None and samples < 1:
            raise CapVectorError(
                f"reasoning samples must be at least 1 (or None: all), got {samples}"
            )
        self.question = question
        self.prompt_template = prompt_template
        self.samples = samples

    def bind(self, backbone: VLABackbone) -> None:
        # The LM head trains with the text objective, unless the run is LoRA (then only adapters
        # and action heads train, as everywhere else).
        if any(".lora_" in name for name, _ in backbone.named_parameters()):
            return
        head = set(backbone.language_head_parameter_names())
        for name, param in backbone.named_parameters():
            if name in head:
                param.requires_grad_(True)

    def forward(self, batch: Batch, output: VLAOutput, backbone: VLABackbone) -> Tensor:
        # Only the answer positions reach the vocabulary projection (the same loss as scoring
        # every position with label -100 elsewhere, without the (B, S, V) logits).
        logits, labels = backbone.answer_logits(*self.text_inputs(batch))
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
