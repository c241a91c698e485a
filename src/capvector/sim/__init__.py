"""The simulator side: robosuite environments, scripted experts, demo recording and rollouts.

Nothing here knows about Lightning or models. A policy is any callable ``observation -> (T, 7)``
array; see :mod:`capvector.sim.rollout`.

Modules (import the one you need; importing this package stays cheap):

- :mod:`~capvector.sim.envs`: task table, ``SimEnv`` (robosuite env + fast camera renderer)
- :mod:`~capvector.sim.experts`: scripted experts (Lift, Stack, PickPlaceCan)
- :mod:`~capvector.sim.annotations`: per-step text about what the expert does and where things are
- :mod:`~capvector.sim.demos`: ``capvector demos``, recording to robomimic/LIBERO-layout HDF5
- :mod:`~capvector.sim.policy`: the policy interface (``Observation``, ``EpisodeResult``)
- :mod:`~capvector.sim.rollout`: ``run_episode`` / ``run_episodes`` for a policy
- :mod:`~capvector.sim.video`: ``write_video``
- :mod:`~capvector.sim.libero`: LIBERO adapter following the OpenVLA-OFT / openpi protocol
"""

import os

# MuJoCo picks its OpenGL backend from MUJOCO_GL when `mujoco` is first imported and defaults to
# GLFW, which needs a display. Our machines are headless (and may have no GPU: EGL then runs on
# Mesa's software rasteriser), so default to EGL before any submodule imports mujoco. robosuite
# forces EGL too, but only at its own import and only when the variable is not osmesa/glx; a user
# who exports MUJOCO_GL=osmesa keeps it.
os.environ.setdefault("MUJOCO_GL", "egl")
