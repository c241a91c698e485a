"""Loss modules attached to a VLAModule by callbacks: auxiliary objectives and regularisers."""

from capvector.objectives.base import OBJECTIVES, Objective
from capvector.objectives.reasoning import ReasoningCoTraining
from capvector.objectives.spatial import SpatialAlignment
from capvector.objectives.teachers import (
    TEACHERS,
    ExternalTeacher,
    GeometricTeacher,
    Teacher,
    TimmTeacher,
)

__all__ = [
    "OBJECTIVES",
    "TEACHERS",
    "ExternalTeacher",
    "GeometricTeacher",
    "Objective",
    "ReasoningCoTraining",
    "SpatialAlignment",
    "Teacher",
    "TimmTeacher",
]
