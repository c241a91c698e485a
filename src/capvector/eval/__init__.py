"""Evaluation: episodes in, success out. The one place that reaches the simulator for rollouts.

Importing this package, ``episodes``, ``results``, ``metrics`` and ``comparison``
imports neither robosuite nor MuJoCo (training code may use them freely); ``rollout`` does, so
``VLAModule`` imports it only when its validation loop rolls out.

- :mod:`~capvector.eval.episodes`: ``EpisodeSpec``, ``LiberoEpisodeSpec``, evaluation and
  validation seeds
- :mod:`~capvector.eval.rollout`: ``RolloutEvaluator``, the one rollout loop every evaluation uses
  (one episode at a time, or batched: many in flight, one policy call per round)
- :mod:`~capvector.eval.workers`: the worker processes that step batched episodes' simulators
- :mod:`~capvector.eval.video`: ``write_video``
- :mod:`~capvector.eval.metrics`: ``SuccessRate``, the validation loop's metric across ranks
- :mod:`~capvector.eval.results`: success rows, Wilson intervals, the one success-table writer
- :mod:`~capvector.eval.comparison`: differences between arms with paired bootstrap intervals
"""
