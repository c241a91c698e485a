"""One registry for every plugin kind: each resolves a registered name and a ``module:Class`` import
path, and an unknown name is one line naming the close ones.

(The entry-point route for backbones from another package runs in tests/test_backbone_registry.py.)
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from capvector.backbones.base import FAMILIES, PRESETS, BackboneError, build_backbone
from capvector.backbones.pi05 import Pi05, pi05_tiny
from capvector.backbones.starvla.heads import ACTION_HEADS, GR00THead
from capvector.errors import CapVectorError
from capvector.objectives import (
    OBJECTIVES,
    TEACHERS,
    ExternalTeacher,
    GeometricTeacher,
    ReasoningCoTraining,
    SpatialAlignment,
)
from capvector.profiling.flops import make_objective
from capvector.registry import Registry

KINDS = {
    # registry: (registered name, what it names, module:Name, a typo of the name)
    "family": (FAMILIES, "pi05", Pi05, "capvector.backbones.pi05.modeling:Pi05", "pi5"),
    "preset": (PRESETS, "pi05-tiny", pi05_tiny, "capvector.backbones.pi05:pi05_tiny", "pi05-tinny"),
    "head": (
        ACTION_HEADS,
        "gr00t",
        GR00THead,
        "capvector.backbones.starvla.heads:GR00THead",
        "groot",
    ),
    "teacher": (
        TEACHERS,
        "geometric",
        GeometricTeacher,
        "capvector.objectives.teachers:GeometricTeacher",
        "geometrik",
    ),
    "objective": (
        OBJECTIVES,
        "reasoning",
        ReasoningCoTraining,
        "capvector.objectives.reasoning:ReasoningCoTraining",
        "reasoming",
    ),
}


@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_resolves_by_name_and_by_import_path(kind: str) -> None:
    registry, name, expected, path, _ = KINDS[kind]
    assert name in registry.names()
    assert registry.get(name) is expected
    assert registry.get(path) is expected


@pytest.mark.parametrize("kind", KINDS)
def test_a_typo_is_one_line_naming_the_close_name(kind: str) -> None:
    registry, name, _, _, typo = KINDS[kind]
    with pytest.raises(CapVectorError) as caught:
        registry.get(typo)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"unknown {registry.kind} {typo!r} (did you mean ")
    assert name in message.split("(did you mean ", 1)[1].split(")")[0]


def test_the_names_reach_what_uses_them() -> None:
    """Configs and tools spell plugins as before, and may name them by import path too."""
    assert isinstance(make_objective("spatial"), SpatialAlignment)
    assert isinstance(
        make_objective("capvector.objectives:ReasoningCoTraining"), ReasoningCoTraining
    )
    assert isinstance(SpatialAlignment(teacher="geometric").teacher, GeometricTeacher)
    assert isinstance(SpatialAlignment().teacher, GeometricTeacher)
    with pytest.raises(CapVectorError, match="teacher 'timm' needs model_name, weights: give it"):
        SpatialAlignment(teacher="timm")
    model = build_backbone("starvla-tiny-gr00t", head="capvector.backbones.starvla.heads:GR00THead")
    assert isinstance(model.action_head, GR00THead)
    with pytest.raises(BackboneError, match=r"unknown action head 'gr00tt' \(did you mean gr00t"):
        build_backbone("starvla-tiny-oft", head="gr00tt")
    with pytest.raises(CapVectorError, match=r"unknown objective 'spatail' \(did you mean spatial"):
        make_objective("spatail")


OUTSIDE = """
import torch
from torch import nn

from capvector.objectives import Teacher


class ConstantTeacher(Teacher):
    feature_dim = 4

    def forward(self, batch, grid):
        return torch.zeros(batch["images"].shape[0], grid[0] * grid[1], 4)


class FeatureMap(nn.Module):
    def forward(self, images):
        return torch.zeros(images.shape[0], 4, 2, 2)


def helper():
    pass
"""


@pytest.fixture
def outside_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    (tmp_path / "outside_plugins.py").write_text(OUTSIDE)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "outside_plugins"
    sys.modules.pop("outside_plugins", None)


def test_a_class_of_another_package_needs_no_registration(outside_module: str) -> None:
    teacher = SpatialAlignment(teacher=f"{outside_module}:ConstantTeacher").teacher
    assert type(teacher).__name__ == "ConstantTeacher"
    with pytest.raises(CapVectorError, match=r"outside_plugins:helper is not a teacher"):
        TEACHERS.get(f"{outside_module}:helper")
    with pytest.raises(CapVectorError, match=r"unknown teacher 'Constant' in module"):
        TEACHERS.get(f"{outside_module}:Constant")
    with pytest.raises(CapVectorError, match=r"cannot import teacher module 'no_such_module'"):
        TEACHERS.get("no_such_module:ConstantTeacher")


def test_the_external_teacher_takes_either_import_path(outside_module: str) -> None:
    for path in (f"{outside_module}:FeatureMap", f"{outside_module}.FeatureMap"):
        assert type(ExternalTeacher(path, feature_dim=4).model).__name__ == "FeatureMap"
    with pytest.raises(CapVectorError, match=r"has no 'FeatureMapp' \(did you mean FeatureMap\?\)"):
        ExternalTeacher(f"{outside_module}:FeatureMapp", feature_dim=4)


def test_registering_twice_fails_and_scoped_registrations_are_undone() -> None:
    registry: Registry[type] = Registry("widget")
    with registry.scoped():

        @registry.register("a")
        class A:
            pass

        registry.register("a")(A)  # the same class again (a module imported twice) is fine
        with pytest.raises(ValueError, match="widget 'a' is registered twice"):
            registry.register("a")(type("B", (), {}))
        assert registry.names() == ["a"]
    assert registry.names() == []
