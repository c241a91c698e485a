"""Evaluation, suite-agnostic: episode specs in, success out. Each spec's suite
(:mod:`capvector.envs.registry`) starts its episode; the loop here drives it.

Importing this package, ``results``, ``metrics`` and ``comparison``
imports neither robosuite nor MuJoCo (training code may use them freely); ``rollout`` does, so
``VLAModule`` imports it only when its validation loop rolls out.

- :mod:`~capvector.eval.rollout`: ``RolloutEvaluator``, the one rollout loop every evaluation uses
  (one episode at a time, or batched: many in flight, one policy call per round)
- :mod:`~capvector.eval.workers`: the worker processes that step batched episodes' simulators
- :mod:`~capvector.eval.video`: ``write_video``
- :mod:`~capvector.eval.metrics`: ``SuccessRate``, the validation loop's metric across ranks
- :mod:`~capvector.eval.results`: success rows, Wilson intervals, the one success-table writer
- :mod:`~capvector.eval.comparison`: differences between arms with paired bootstrap intervals
"""
