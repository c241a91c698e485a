"""Loss modules attached to a VLAModule by callbacks: auxiliary objectives and regularisers."""

from capvector.objectives.base import Objective
from capvector.objectives.reasoning import ReasoningCoTraining
from capvector.objectives.spatial import SpatialAlignment
from capvector.objectives.teachers import ExternalTeacher, GeometricTeacher, Teacher, TimmTeacher

__all__ = [
    "ExternalTeacher",
    "GeometricTeacher",
    "Objective",
    "ReasoningCoTraining",
    "SpatialAlignment",
    "Teacher",
    "TimmTeacher",
]
