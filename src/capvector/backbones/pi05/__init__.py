"""Pi0.5 (openpi, LeRobot's pi05): ``configuration.py`` holds the config and presets,
``modeling.py`` the model, ``convert.py`` the reading of LeRobot and openpi checkpoints (imported
only by ``Pi05.from_original``). Importing the package registers the presets and the family.
"""

from capvector.backbones.pi05 import configuration, modeling
from capvector.backbones.pi05.configuration import *  # noqa: F403 (its __all__)
from capvector.backbones.pi05.modeling import *  # noqa: F403 (its __all__)

__all__ = [*configuration.__all__, *modeling.__all__]
