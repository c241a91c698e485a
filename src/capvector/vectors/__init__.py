"""Capability-vector math and IO: extract, merge, low-rank/PEFT, compose, inspect.

Works on state dicts and safetensors files and knows nothing of Lightning, so the CLI
(``capvector extract|merge|compose|inspect``) and the training callbacks share one implementation.
"""

from capvector.vectors.compose import compose
from capvector.vectors.extract import extract
from capvector.vectors.inspect import InspectReport, inspect_vector
from capvector.vectors.io import CapVectorError, open_weights
from capvector.vectors.lowrank import LoraFactors, svd_factors
from capvector.vectors.merge import add_scaled, apply_vector_, match_tensors, merge, validate_vector
from capvector.vectors.vector import CapabilityVector, VectorFolder, load_vector

__all__ = [
    "CapVectorError",
    "CapabilityVector",
    "InspectReport",
    "LoraFactors",
    "VectorFolder",
    "add_scaled",
    "apply_vector_",
    "compose",
    "extract",
    "inspect_vector",
    "load_vector",
    "match_tensors",
    "merge",
    "open_weights",
    "svd_factors",
    "validate_vector",
]
