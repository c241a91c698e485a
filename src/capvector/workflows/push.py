"""``capvector push``: upload an export or a vector folder, with its model card, to a Hugging Face
Hub model repository; a hub id names it afterwards wherever capvector takes a folder."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from capvector.errors import CapVectorError
from capvector.io.hub import commit_operations
from capvector.io.modelcard import read_model_card
from capvector.io.names import ADAPTER_CONFIG, EXPORT_CONFIG, VECTOR_META
from capvector.tool_cli import run_tool

if TYPE_CHECKING:
    from huggingface_hub import CommitOperationAdd


def upload_plan(folder: str | Path) -> tuple[str, list[CommitOperationAdd]]:
    """What ``push`` sends: the folder's kind (``export`` or ``vector``), checked as capvector
    reads it, and one commit operation per file. Refused: a folder that is neither, or whose
    model card is missing, broken or has a local path as ``base_model``."""
    path = Path(folder)
    if not path.is_dir():
        raise CapVectorError(f"{folder} is not a folder: push takes an export or vector folder")
    if (path / VECTOR_META).is_file() or (path / ADAPTER_CONFIG).is_file():
        from capvector.vectors.vector import VectorFolder

        kind = "vector"
        VectorFolder(path)  # its files match its metadata, or one line says what is wrong
    elif (path / EXPORT_CONFIG).is_file():
        from capvector.backbones.base import load_export_config

        kind = "export"
        load_export_config(path)
    else:
        raise CapVectorError(
            f"{folder} is neither an export ({EXPORT_CONFIG}) nor a vector folder ({VECTOR_META}): "
            "push uploads what capvector export, merge, import-original or extract wrote"
        )
    read_model_card(path)
    return kind, commit_operations(path)


def push(
    folder: str,
    repo_id: str,
    /,
    *,
    private: bool = False,
    revision: str | None = None,
    message: str | None = None,
    dry_run: bool = False,
) -> None:
    """Upload an export or a vector folder with its model card to a Hugging Face Hub model repo
    (created when missing), in one commit. Needs a token (`hf auth login` or HF_TOKEN).

    Args:
        folder: export or vector folder
        repo_id: the hub repository, org/name
        private: create the repository private
        revision: the branch to commit to (default: main)
        message: the commit message
        dry_run: list the files and check the card, upload nothing
    """
    from huggingface_hub import HfApi
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id

    try:
        validate_repo_id(repo_id)
    except HFValidationError as err:
        raise CapVectorError(f"REPO_ID {repo_id!r} is not a hub repository id (org/name)") from err
    kind, operations = upload_plan(folder)
    for operation in operations:
        print(f"  {operation.path_in_repo}")
    if dry_run:
        print(f"{kind} {folder}: {len(operations)} files, model card valid; nothing uploaded")
        return
    api = HfApi()
    # Offline, unreachable, no token, no write access: huggingface_hub raises its own errors, OSErrors
    # or (since 1.0) its HTTP client's, so every failure of the upload is one line.
    try:
        api.create_repo(repo_id, repo_type="model", private=private, exist_ok=True)
        commit = api.create_commit(
            repo_id,
            operations,
            commit_message=message or f"capvector push: {kind} {Path(folder).name}",
            revision=revision,
        )
    except Exception as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CapVectorError(f"could not upload to {repo_id} ({first})") from err
    print(f"pushed {kind} {folder} to {commit.commit_url}")


def main(argv: list[str] | None = None) -> int:
    return run_tool(push, argv, "push")
