"""The files capvector reads and writes; the bottom layer (it imports nothing else of capvector but
``errors``, so every other package may use it).

- :mod:`~capvector.io.names`: every file name capvector writes; the checkpoint metadata record
- :mod:`~capvector.io.outputs`: checks before any work, and atomic writes of every output
- :mod:`~capvector.io.loading`: weight and JSON files read with one clear error when cut short
- :mod:`~capvector.io.weights`: model weights (export folders, Lightning checkpoints) read tensor
  by tensor, content fingerprints, streaming safetensors writes
- :mod:`~capvector.io.lora_layers`: peft LoRA layers in state dicts, found and merged
- :mod:`~capvector.io.modelcard`: the ``README.md`` model card of export and vector folders
"""
