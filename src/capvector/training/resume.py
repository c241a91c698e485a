"""What ``capvector fit ... --ckpt_path last`` resumes, and checks a fit's outputs before it starts.

Lightning resolves ``ckpt_path="last"`` inside the run folder of the *new* logger version, which
is empty, so a plain ``capvector fit --ckpt_path last`` trained from scratch in a new version folder
with only a warning. Here ``last`` means the newest run in the logger's folder that holds a
checkpoint: the fit resumes from it and logs into that same version folder, so its metrics go on.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint

from capvector.errors import CapVectorError
from capvector.io.outputs import Inputs, check_outside_inputs, check_room, check_writable

LAST = "last.ckpt"


def resume_latest_run(trainer: L.Trainer) -> Path:
    """Point the trainer's logger at the newest version folder with a checkpoint; its checkpoint."""
    checkpoint = next(
        (c for c in trainer.callbacks if isinstance(c, ModelCheckpoint) and c.dirpath), None
    )
    if checkpoint is not None:  # an explicit checkpoint folder: the logger version does not matter
        found = _newest_checkpoint(Path(checkpoint.dirpath))
        if found is None:
            raise CapVectorError(
                f"--ckpt_path last: {checkpoint.dirpath} holds no checkpoint; pass a .ckpt path, or "
                "drop --ckpt_path to start a new run"
            )
        return found
    logger = trainer.logger
    root = Path(logger.root_dir) if logger is not None and hasattr(logger, "root_dir") else None
    if root is None:
        found = _newest_checkpoint(Path(trainer.default_root_dir) / "checkpoints")
        where = Path(trainer.default_root_dir) / "checkpoints"
    else:
        found = None
        for version_dir in _versions_newest_first(root):
            found = _newest_checkpoint(version_dir / "checkpoints")
            if found is not None:
                logger._version = int(version_dir.name.removeprefix("version_"))  # type: ignore[union-attr]
                break
        where = root / "version_*" / "checkpoints"
    if found is None:
        raise CapVectorError(
            f"--ckpt_path last: no checkpoint under {where}; pass the path of a .ckpt "
            f"(e.g. <run>/checkpoints/{LAST}), or drop --ckpt_path to start a new run"
        )
    return found


def check_ckpt_path(ckpt_path: str | None) -> None:
    """Fail first when ``--ckpt_path`` names a local checkpoint Lightning could not read: missing,
    or cut short (a run killed while saving it, an incomplete copy), which LightningCLI and the
    fit's restore otherwise report as a miniz traceback. Lightning's keywords (``last``, ``best``,
    ``hpc``, ``registry:...``), URLs and checkpoint folders (DeepSpeed, sharded) are left to it."""
    if ckpt_path in (None, "last", "best", "hpc") or re.match(r"\w+:", str(ckpt_path)):
        return
    path = Path(str(ckpt_path))
    if path.is_dir():
        return
    if not path.is_file():
        raise CapVectorError(
            f"--ckpt_path {path} does not exist; pass an existing .ckpt, or drop --ckpt_path to "
            "start a new run"
        )
    try:  # torch checkpoints are zip archives: reading the directory at the end finds a cut
        with zipfile.ZipFile(path):
            pass
    except (zipfile.BadZipFile, OSError) as err:
        raise CapVectorError(
            f"--ckpt_path {path} is incomplete or corrupt ({err}): the run stopped while saving "
            "it, or a copy was cut short; delete it (--ckpt_path last then takes the newest "
            "checkpoint left) or pass another --ckpt_path"
        ) from err


def check_fit_outputs(trainer: L.Trainer, model: L.LightningModule, inputs: Inputs = ()) -> None:
    """Fail before training (nothing written yet) when a folder the fit writes to could not be
    created, is or lies inside one of the fit's ``inputs`` (a fit once trained every step into
    its pretrained export and failed at the end), or its disk has no room for a checkpoint and
    the export."""
    paths = [("trainer.default_root_dir", trainer.default_root_dir)]
    for logger in trainer.loggers:
        if getattr(logger, "save_dir", None):
            paths.append((f"the {type(logger).__name__}'s save_dir", logger.save_dir))
    for callback in trainer.callbacks:  # ModelCheckpoint, ExportOnFitEnd: the folder they write
        if getattr(callback, "dirpath", None):
            paths.append((f"{type(callback).__name__}'s dirpath", callback.dirpath))
    needed = fit_output_bytes(model, checkpoints=bool(trainer.checkpoint_callbacks))
    for what, path in paths:
        check_outside_inputs(path, inputs, what, may_hold=True)
        check_writable(path, f"into {what}", inside=True)
        check_room(path, needed, what)


def fit_output_bytes(model: L.LightningModule, checkpoints: bool) -> int:
    """About what a fit writes at least: its export (every weight) and, with checkpoints, one
    checkpoint (every weight again, and Adam's two float32 moments of each trained one)."""
    weights = sum(p.numel() * p.element_size() for p in model.parameters())
    trained = sum(p.numel() for p in model.parameters() if p.requires_grad)
    return weights + (weights + 2 * 4 * trained if checkpoints else 0)


def _versions_newest_first(root: Path) -> list[Path]:
    versions = [p for p in root.glob("version_*") if re.fullmatch(r"version_\d+", p.name)]
    return sorted(versions, key=lambda p: int(p.name.removeprefix("version_")), reverse=True)


def _newest_checkpoint(folder: Path) -> Path | None:
    if (folder / LAST).is_file():
        return folder / LAST
    checkpoints = sorted(folder.glob("*.ckpt"), key=lambda p: p.stat().st_mtime)
    return checkpoints[-1] if checkpoints else None
