"""Meta-World (Farama-Foundation/Metaworld 3.1.1): 50 Sawyer tabletop tasks, MT10 and MT50, under
LeRobot's evaluation protocol (:mod:`capvector.envs.metaworld.spec`)."""
