"""The simulator: robosuite environments, scripted experts, demo recording, LIBERO's envs.

Nothing here knows about Lightning or models. A policy is any callable ``observation -> (T, 7)``
array (:mod:`~capvector.sim.policy`); evaluation runs policies here through
:mod:`capvector.eval.rollout`.

Modules (import the one you need; importing this package, ``tasks``, ``policy`` and ``variants``
imports neither robosuite nor MuJoCo):

- :mod:`~capvector.sim.tasks`: the task table (instructions, objects, step limits)
- :mod:`~capvector.sim.variants`: zero-shot robustness variants (camera, lighting, colour, arm)
- :mod:`~capvector.sim.envs`: ``SimEnv`` (robosuite env + fast camera renderer); sets ``MUJOCO_GL``
- :mod:`~capvector.sim.fast_control`: the controller substeps of ``SimEnv``'s fast step
- :mod:`~capvector.sim.experts`: scripted experts (Lift, Stack, PickPlaceCan)
- :mod:`~capvector.sim.annotations`: per-step text about what the expert does and where things are
- :mod:`~capvector.sim.demos`: ``capvector demos``, recording to robomimic/LIBERO-layout HDF5
- :mod:`~capvector.sim.policy`: the policy interface (``Observation``, ``EpisodeResult``)
- :mod:`~capvector.sim.libero`: LIBERO's envs and the OpenVLA-OFT / openpi protocol's constants
- :mod:`~capvector.sim.libero_render`: LIBERO's scenes rendered ~13x cheaper on a CPU, same physics
"""
