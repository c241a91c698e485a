"""LIBERO's task suites under the OpenVLA-OFT / openpi evaluation protocol: environments, episodes,
fast rendering, scripted experts and demos in LIBERO's released layout (see :mod:`capvector.envs`)."""
