"""What a training run will cost, from a meta-device build (``capvector backbone-info``).

- :mod:`~capvector.profiling.memory`: per-device training memory, activations measured by a trace
- :mod:`~capvector.profiling.flops`: training FLOPs per sample and GPU-hours
"""
