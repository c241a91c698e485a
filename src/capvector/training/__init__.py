"""The training core beside ``capvector.module`` (``VLAModule``) and ``capvector fit``.

- :mod:`~capvector.training.lora`: LoRA through peft: injection, what trains, frozen dtypes
- :mod:`~capvector.training.distributed`: FSDP2 sharding, activation checkpointing, sharded state
- :mod:`~capvector.training.resume`: what ``--ckpt_path last`` resumes; a fit's outputs checked
  before it starts
- :mod:`~capvector.training.loggers`: a CSV logger whose history survives a resumed fit
- :mod:`~capvector.training.threads`: a fit's torch threads, its share of the CPUs beside other fits
"""
