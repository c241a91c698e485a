"""What has been merged into a model: a list of vectors by content fingerprint and λ.

The record travels with the weights (an export's ``config.json`` and a Lightning checkpoint's
``capvector`` metadata under ``merged_vectors``), so whether a vector is already in a model does not
depend on how its folder path is spelled, nor on which callbacks a resumed run was given. The
fingerprint hashes every tensor of the vector (``VectorFolder.fingerprint``, checked against the one
recorded when the vector was written). Entries written before content fingerprints hold a sampled
"sha256:" one that no folder reproduces; they are matched by the folder's path instead.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from capvector.io.names import MERGED_VECTORS  # noqa: F401 (re-exported: the record's field)
from capvector.io.weights import FINGERPRINT_PREFIX, CapVectorError, short_fingerprint
from capvector.vectors.vector import VectorFolder

BY_MERGE = "capvector merge"
BY_FIT_START = "MergeCapabilityVector"


@dataclass(frozen=True)
class MergedVector:
    """One vector merged into a model."""

    fingerprint: str
    """``VectorFolder.fingerprint()``: the identity of the vector's tensors, not of their path."""
    scale: float
    path: str
    """Where the folder was when it was merged (for people; compared only for entries recorded
    before content fingerprints)."""
    by: str
    """``capvector merge`` or ``MergeCapabilityVector`` (at fit start)."""

    @classmethod
    def of(cls, folder: str | Path | VectorFolder, scale: float, by: str) -> MergedVector:
        vector = folder if isinstance(folder, VectorFolder) else VectorFolder(folder)
        return cls(vector.fingerprint(), float(scale), str(vector.path.resolve()), by)

    def describe(self) -> str:
        return f"{self.path} x {self.scale:g} ({short_fingerprint(self.fingerprint)}, by {self.by})"

    def same_vector(self, other: MergedVector) -> bool:
        if self.fingerprint.startswith(FINGERPRINT_PREFIX):
            return self.fingerprint == other.fingerprint
        return self.path == other.path  # a sampled fingerprint: the path is all that is comparable

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def read_record(entries: Sequence[dict[str, Any]] | None) -> list[MergedVector]:
    return [MergedVector(**entry) for entry in entries or []]


def record_dicts(record: Sequence[MergedVector]) -> list[dict[str, Any]]:
    return [entry.to_dict() for entry in record]


def check_not_merged(
    record: Sequence[MergedVector], entry: MergedVector, model: str, allow_repeat: bool
) -> None:
    """Refuse to merge ``entry`` into a model whose record already holds the same vector."""
    held = [r for r in record if r.same_vector(entry)]
    if held and not allow_repeat:
        raise CapVectorError(
            f"{model} already holds vector {entry.path}: it was merged as {held[0].describe()}. "
            "Merging it again counts it twice; start from the model without it, or allow it "
            "explicitly (--allow-repeat / allow_repeat: true)"
        )


def check_resumed(record: Sequence[MergedVector], entry: MergedVector, checkpoint: str) -> None:
    """On resume: the checkpoint must record ``entry`` as merged at fit start, with the same λ."""
    at_fit_start = [r for r in record if r.by == BY_FIT_START]
    same = [r for r in at_fit_start if r.same_vector(entry)]
    if same and math.isclose(same[0].scale, entry.scale, rel_tol=1e-9, abs_tol=1e-12):
        return
    if same:
        raise CapVectorError(
            f"checkpoint {checkpoint} merged {same[0].describe()}; this resume asks for "
            f"{entry.describe()}. Resume with scale {same[0].scale:g}, or start a new fit"
        )
    recorded = "; ".join(r.describe() for r in at_fit_start) or "no vector at fit start"
    raise CapVectorError(
        f"checkpoint {checkpoint} records {recorded}; this resume asks for {entry.describe()}. "
        "Resume with the vector the run started with, or start a new fit"
    )
