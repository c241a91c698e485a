"""robosuite 1.5 tasks as a suite: the task table, environments, scripted experts, demos and
zero-shot variants (see :mod:`capvector.envs`)."""
