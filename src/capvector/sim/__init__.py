"""The simulator side: robosuite environments, scripted experts, demo recording and rollouts.

Nothing here knows about Lightning or models. A policy is any callable ``observation -> (T, 7)``
array; see :mod:`capvector.sim.rollout`.

Modules (import the one you need; importing this package, ``tasks``, ``episodes``, ``policy`` and
``variants`` imports neither robosuite nor MuJoCo — training code may use them freely):

- :mod:`~capvector.sim.tasks`: the task table (instructions, objects, step limits)
- :mod:`~capvector.sim.episodes`: ``EpisodeSpec``, evaluation and validation seeds
- :mod:`~capvector.sim.variants`: zero-shot robustness variants (camera, lighting, colour, arm)
- :mod:`~capvector.sim.envs`: ``SimEnv`` (robosuite env + fast camera renderer); sets ``MUJOCO_GL``
- :mod:`~capvector.sim.experts`: scripted experts (Lift, Stack, PickPlaceCan)
- :mod:`~capvector.sim.annotations`: per-step text about what the expert does and where things are
- :mod:`~capvector.sim.demos`: ``capvector demos``, recording to robomimic/LIBERO-layout HDF5
- :mod:`~capvector.sim.policy`: the policy interface (``Observation``, ``EpisodeResult``)
- :mod:`~capvector.sim.rollout`: ``RolloutEvaluator``, the one rollout loop every evaluation uses
  (one episode at a time, or batched: many in flight, one policy call per round)
- :mod:`~capvector.sim.workers`: the worker processes that step batched episodes' simulators
- :mod:`~capvector.sim.video`: ``write_video``
- :mod:`~capvector.sim.libero`: LIBERO adapter following the OpenVLA-OFT / openpi protocol
"""
