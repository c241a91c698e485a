"""Thin Lightning callbacks: they attach, schedule and persist; the math lives elsewhere."""

from capvector.callbacks.auxiliary import AuxiliaryObjective
from capvector.callbacks.capability import MergeCapabilityVector, OrthogonalRegularization
from capvector.callbacks.checkpoint import CheckpointAfterValidation
from capvector.callbacks.export import ExportOnFitEnd
from capvector.callbacks.requeue import RequeueAtStepEnd
from capvector.callbacks.step_cost import StepCost
from capvector.callbacks.threads import ShareCores

__all__ = [
    "AuxiliaryObjective",
    "CheckpointAfterValidation",
    "ExportOnFitEnd",
    "MergeCapabilityVector",
    "OrthogonalRegularization",
    "RequeueAtStepEnd",
    "ShareCores",
    "StepCost",
]
