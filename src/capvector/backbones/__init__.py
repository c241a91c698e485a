"""VLA backbones behind one contract (``VLABackbone``), built from registered presets."""

from capvector.backbones.base import (
    BackboneConfig,
    BackboneError,
    ImportOption,
    OriginalCheckpoint,
    OutputRequest,
    VLABackbone,
    VLAOutput,
    backbone_class,
    build_backbone,
    from_pretrained,
    list_presets,
    preset_config,
    register_family,
    register_preset,
)

__all__ = [
    "BackboneConfig",
    "BackboneError",
    "ImportOption",
    "OriginalCheckpoint",
    "OutputRequest",
    "VLABackbone",
    "VLAOutput",
    "backbone_class",
    "build_backbone",
    "from_pretrained",
    "list_presets",
    "preset_config",
    "register_family",
    "register_preset",
]
