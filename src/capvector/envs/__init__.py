"""The benchmarks: simulated suites a policy is evaluated in and demonstrations are recorded from.

Nothing here knows about Lightning or models. A policy is any callable ``observation -> (T, 7)``
array (:mod:`~capvector.envs.base`); evaluation runs policies here through
:mod:`capvector.eval.rollout`.

One package per suite (import the module you need; importing this package, ``base``,
``robosuite.tasks`` and ``robosuite.variants`` imports neither robosuite nor MuJoCo):

- :mod:`~capvector.envs.base`: the ``Suite`` contract and the policy interface (``Observation``,
  ``EpisodeResult``); :mod:`~capvector.envs.registry`: the suites by name
- :mod:`~capvector.envs.recording`: recording demos for every suite (the attempt loop, the writer)
- :mod:`~capvector.envs.robosuite`: robosuite 1.5 tasks (Lift, Stack, PickPlaceCan, ...)

  - ``tasks``: the task table (instructions, objects, step limits)
  - ``variants``: zero-shot robustness variants (camera, lighting, colour, arm)
  - ``env``: ``SimEnv`` (robosuite env + fast camera renderer); sets ``MUJOCO_GL``
  - ``fast_control``: the controller substeps of ``SimEnv``'s fast step (LIBERO's envs use it too)
  - ``experts``: scripted experts (Lift, Stack, PickPlaceCan)
  - ``annotations``: per-step text about what the expert does and where things are
  - ``demos``: its demos' datasets (robomimic layout), recorded through ``recording``

- :mod:`~capvector.envs.libero`: LIBERO's task suites, built on robosuite

  - ``env``: LIBERO's envs and the OpenVLA-OFT / openpi protocol's constants
  - ``episode``: ``LiberoEpisode``, a LIBERO trial under the official protocol
  - ``render``: LIBERO's scenes rendered ~13x cheaper on a CPU, same physics
  - ``experts``: scripted pick-and-place experts read from the BDDL goal
  - ``annotations``: per-step text for LIBERO scenes
  - ``demos``: its demos in LIBERO's released HDF5 layout, recorded through ``recording``

- :mod:`~capvector.envs.metaworld`: Meta-World's 50 tasks (MT10, MT50) under LeRobot's protocol

  - ``spec``: task sets, instructions, the protocol's constants
  - ``env``: ``MetaWorldEnv`` (7-d actions to Meta-World's 4, proprio, corner2 upright)
  - ``episode``, ``experts`` (Meta-World's scripted policies), ``demos`` (robomimic layout)
"""
