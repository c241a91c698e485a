"""Capability-vector math: extract, merge, low-rank/PEFT, compose, inspect, the merge record.

Works on state dicts and safetensors files (read and written through :mod:`capvector.io.weights`)
and knows nothing of Lightning, so the CLI
(``capvector extract|merge|compose|inspect``) and the training callbacks share one implementation.
"""

from capvector.io.weights import CapVectorError, open_weights
from capvector.vectors.compose import compose
from capvector.vectors.extract import extract
from capvector.vectors.inspect import InspectReport, inspect_vector
from capvector.vectors.lowrank import LoraFactors, svd_factors
from capvector.vectors.merge import add_scaled, apply_vector_, match_tensors, merge, validate_vector
from capvector.vectors.record import MergedVector, read_record, record_dicts
from capvector.vectors.vector import CapabilityVector, VectorFolder, load_vector

__all__ = [
    "CapVectorError",
    "CapabilityVector",
    "InspectReport",
    "LoraFactors",
    "MergedVector",
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
    "read_record",
    "record_dicts",
    "svd_factors",
    "validate_vector",
]
