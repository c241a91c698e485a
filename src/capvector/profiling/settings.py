"""The training run an estimate is for, declared once for ``estimate_memory`` and for
``backbone-info``'s options (the tool gives each field an option of its own). Plain Python, so the
CLI can read it without importing torch."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TrainingSettings:
    """What the training run does that changes its cost per device.

    Attributes:
        batch: per-device batch size
        precision: trainer.precision: 32-true, bf16-mixed or bf16-true
        strategy: ddp, fsdp2, deepspeed_zero2 or deepspeed_zero3
        devices: devices the model is sharded over
        lora_rank: train LoRA of this rank (none: the whole model trains)
        frozen_dtype: storage dtype of the parameters that do not train (model.frozen_dtype)
        attention: SDPA as a GPU runs it, efficient (efficient/flash kernels: no S x S attention
            matrix kept), or math (what the meta device and some CPUs take)
        activation_checkpointing: the total assumes model.activation_checkpointing: true (both
            figures are always reported)
        objectives: auxiliary objectives attached, by name (spatial, reasoning: aux_sft.yaml's
            pair, with their defaults); their cost is a term of its own
        vector: a capability vector folder merged at fit start (MergeCapabilityVector) with
            OrthogonalRegularization in LoRA mode; its cost is a term of its own
        vector_float32_weights: MergeCapabilityVector's ``float32_weights``: the frozen weights
            the vector changes stay float32
    """

    batch: int = 8
    precision: str = "bf16-mixed"
    strategy: str = "fsdp2"
    devices: int = 1
    lora_rank: int | None = None
    frozen_dtype: str = "float32"
    attention: str = "efficient"
    activation_checkpointing: bool = False
    objectives: tuple[str, ...] = ()
    vector: str | None = None
    vector_float32_weights: bool = True
