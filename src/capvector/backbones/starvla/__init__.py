"""StarVLA (starVLA/starVLA): a Qwen-VL plus a pluggable action head. ``configuration.py`` holds
the config and presets, ``modeling.py`` the model, ``heads.py`` the action heads and their registry
(``register_head``), ``convert.py`` the reading of StarVLA runs (imported only by
``StarVLA.from_original``). Importing the package registers the presets, heads and family.
"""

from capvector.backbones.starvla import configuration, heads, modeling
from capvector.backbones.starvla.configuration import *  # noqa: F403 (its __all__)
from capvector.backbones.starvla.heads import *  # noqa: F403 (its __all__)
from capvector.backbones.starvla.modeling import *  # noqa: F403 (its __all__)

__all__ = [*configuration.__all__, *heads.__all__, *modeling.__all__]
