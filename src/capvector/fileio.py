"""Atomic writes: results appear whole or not at all, with the permissions the umask gives.

``tempfile`` creates private folders (0700) and files (0600), which is right while a result is being
written; once it is complete it gets the modes an ordinary ``mkdir``/``open`` would have given it,
so a shared cluster's group can read exports and vectors as it reads any other file.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from capvector.errors import CapVectorError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _publish_modes(tmp: Path) -> None:
    """Give a finished temporary folder (recursively) or file the modes the umask allows: tempfile
    and some writers (safetensors) create private files."""
    mask = _umask()
    paths = [tmp, *tmp.rglob("*")] if tmp.is_dir() else [tmp]
    for path in paths:
        if not path.is_symlink():
            os.chmod(path, (0o777 if path.is_dir() else 0o666) & ~mask)


def check_writable(path: str | Path, what: str = "output", inside: bool = False) -> Path:
    """Fail before any work when ``path`` could not be created (``inside``: when files could not be
    created inside the folder ``path``): the nearest existing folder must be writable."""
    target = Path(path)
    ancestor = target.absolute() if inside else target.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise CapVectorError(
            f"cannot write {what} {target}: {ancestor} is a file, not a folder; choose another path"
        )
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise CapVectorError(
            f"cannot write {what} {target}: no permission to write in {ancestor}; choose a folder "
            "you can write to"
        )
    return target


def check_new_output(path: str | Path, overwrite: bool, what: str = "--out") -> Path:
    """Fail before any work when ``path`` exists (without ``overwrite``) or could not be written."""
    target = check_writable(path, what)
    if target.exists() and not overwrite:
        raise CapVectorError(f"{target} exists; choose another {what} or pass --overwrite")
    return target


@contextmanager
def atomic_directory(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling folder that replaces ``path`` only if the block succeeds.

    The temporary folder lives beside the target so the final rename stays on one file system.
    """
    target = check_writable(path)
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} exists; choose another output or pass --overwrite")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        yield tmp
        _publish_modes(tmp)
        if target.exists():
            backup = target.with_name(f".{target.name}.old-{os.getpid()}")
            os.replace(target, backup)
            os.replace(tmp, target)
            shutil.rmtree(backup, ignore_errors=True)
        else:
            os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextmanager
def atomic_write_file(path: str | Path) -> Iterator[Path]:
    """A temporary sibling file path that replaces ``path`` (fsynced, renamed) if the block succeeds."""
    target = check_writable(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.tmp-", dir=target.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        _publish_modes(tmp)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write a file through a temporary sibling and an atomic rename."""
    with atomic_write_file(path) as tmp:
        tmp.write_bytes(data)
