"""Hugging Face Hub names: wherever a model, an export or a vector folder is accepted, a hub id
(``org/name``, or ``org/name@revision``) that is not a local path names a hub repository, read
through ``huggingface_hub.snapshot_download`` from the local cache first (so ``HF_HUB_OFFLINE=1``
works for anything downloaded before) and downloaded otherwise. The reverse, uploading a folder,
is ``commit_operations`` (what ``capvector push`` sends).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

from capvector.errors import CapVectorError

if TYPE_CHECKING:
    from huggingface_hub import CommitOperationAdd

_HUB_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+(@[\w./-]+)?")
"""The shape of ``org/name[@revision]``; ``huggingface_hub.utils.validate_repo_id`` decides."""


def hub_id(name: str | Path | None) -> str | None:
    """``name`` when it names a hub repository (``org/name[@revision]``) and no local path (a
    local folder always wins, as in ``transformers``' ``from_pretrained``); else None."""
    if name is None or isinstance(name, Path):
        return None
    text = str(name)
    if not _HUB_ID.fullmatch(text) or Path(text).exists():
        return None
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id

    try:
        validate_repo_id(text.partition("@")[0])
    except HFValidationError:
        return None
    return text


def local_folder(name: str | Path, what: str = "folder") -> Path:
    """The local folder ``name`` names: a path as it is; a hub id as its snapshot's folder, from
    the local cache when it is there (no network), downloaded otherwise unless the hub is
    offline (``HF_HUB_OFFLINE=1``). ``what`` names the input in errors (e.g. ``--ckpt``)."""
    repo = hub_id(name)
    if repo is None:
        return Path(name)
    from huggingface_hub import constants, snapshot_download
    from huggingface_hub.errors import LocalEntryNotFoundError

    repo_id, _, revision = repo.partition("@")
    try:  # the cache first: what was downloaded once is not asked for again
        return Path(snapshot_download(repo_id, revision=revision or None, local_files_only=True))
    except LocalEntryNotFoundError:
        pass
    if constants.HF_HUB_OFFLINE:
        raise CapVectorError(
            f"{what} {name} is no local path, and hub repo {repo} is not in the hub cache "
            f"({constants.HF_HUB_CACHE}) while HF_HUB_OFFLINE is set: download it where the "
            f"network allows (`hf download {repo_id}`) or give a local folder"
        )
    try:
        return Path(snapshot_download(repo_id, revision=revision or None))
    except Exception as err:  # unreachable hub, unknown or private repo, bad revision
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CapVectorError(
            f"{what} {name} is no local path, and hub repo {repo} could not be downloaded "
            f"({first}); check the name, or download it where the network allows and give the "
            "local folder"
        ) from err


def commit_operations(folder: str | Path) -> list[CommitOperationAdd]:
    """One ``CommitOperationAdd`` per file under ``folder`` (recursively, sorted), at its path
    relative to ``folder``: what a hub commit of the folder as it is holds. Hidden files are left
    out (``hf download --local-dir`` keeps its bookkeeping in ``.cache/``)."""
    from huggingface_hub import CommitOperationAdd

    root = Path(folder)
    files = sorted(
        p
        for p in root.rglob("*")
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(root).parts)
    )
    return [
        CommitOperationAdd(path_in_repo=p.relative_to(root).as_posix(), path_or_fileobj=str(p))
        for p in files
    ]
