"""OpenVLA-OFT (moojink/openvla-oft), with OFT+'s FiLM: ``configuration.py`` holds the config and
presets, ``modeling.py`` the model, ``convert.py`` the reading of upstream's run folders (imported
only by ``OpenVLAOFT.from_original``). Importing the package registers the presets and the family.
"""

from capvector.backbones.openvla_oft import configuration, modeling
from capvector.backbones.openvla_oft.configuration import *  # noqa: F403 (its __all__)
from capvector.backbones.openvla_oft.modeling import *  # noqa: F403 (its __all__)

__all__ = [*configuration.__all__, *modeling.__all__]
