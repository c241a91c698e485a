"""Reading weight and JSON files that may be missing, cut short or something else: each failure
is one ``CapVectorError`` that names the file and what to do, not the library's traceback.

A copy or download stopped early leaves a truncated file; safetensors and torch then fail deep in
their own code (``SafetensorError``, miniz ``RuntimeError``, ``EOFError``, ``UnpicklingError``, even
a ``KeyError`` for a pickle that ends early). Only the load call itself is guarded, so an error
raised by our own code after it still shows its traceback.
"""

from __future__ import annotations

import json
import pickle
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capvector.errors import CapVectorError

if TYPE_CHECKING:
    from torch import Tensor

COPY_AGAIN = "copy or download it again"


def load_safetensors(path: str | Path, fix: str = COPY_AGAIN) -> dict[str, Tensor]:
    """All tensors of a safetensors file, on the CPU."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    _check_file(path)
    try:
        return load_file(str(path))
    except (SafetensorError, OSError) as err:
        raise _unreadable(path, err, "safetensors", fix) from err


def load_torch(
    path: str | Path, fix: str = COPY_AGAIN, map_location: str = "cpu", **kwargs: Any
) -> Any:
    """``torch.load(path, map_location, **kwargs)``."""
    import torch

    _check_file(path)
    try:
        return torch.load(path, map_location=map_location, **kwargs)
    except (RuntimeError, pickle.UnpicklingError, EOFError, KeyError, OSError) as err:
        raise _unreadable(path, err, "torch", fix) from err


def read_json(path: str | Path) -> dict[str, Any]:
    """The JSON object in ``path`` (a config, index or metadata file)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CapVectorError(f"cannot read {path}: {err}; {COPY_AGAIN}") from err
    if not isinstance(data, dict):
        raise CapVectorError(f"{path} does not hold a JSON object")
    return data


def _unreadable(path: str | Path, err: BaseException, kind: str, fix: str) -> CapVectorError:
    """The error for a file a library could not read: its reason, first sentence only (torch's
    miniz message goes on for four more)."""
    reason = re.split(r"(?<=\.)\s", str(err).strip(), maxsplit=1)[0] or type(err).__name__
    return CapVectorError(
        f"cannot read {path} ({reason}): it is incomplete, corrupt or not a {kind} file; {fix}"
    )


def _check_file(path: str | Path) -> None:
    if not Path(path).is_file():
        what = "is a folder, not a file" if Path(path).is_dir() else "does not exist"
        raise CapVectorError(f"{path} {what}")
