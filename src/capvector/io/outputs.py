"""Every output a command writes goes through here, so no command can lose data on its own.

- ``check_output``, before any work: an output must not be, hold or lie inside an input (so
  ``--out P --overwrite`` cannot delete the inputs kept in ``P``), must not exist unless
  overwritten, and must be writable.
- ``atomic_directory`` / ``atomic_write_file``: the result is written into a temporary sibling
  ``.NAME.tmp-<pid>-<random>`` and renamed into place only when complete. A lock (``.NAME.lock``) lets one
  process at a time write ``NAME``; the next writer of ``NAME`` sweeps the temporaries of writers
  that died without cleaning up (``kill -9``). Other exits (exceptions, Ctrl-C, and SIGTERM, which
  the CLI turns into an exception) remove their temporary on the way out.
- A full disk while writing is bad input of the output's place, not a crash: ``no_room`` names the
  path and its free space; ``check_room`` refuses up front when a writer knows what it needs.
- ``--overwrite`` replaces a folder only when capvector wrote it (it holds ``MARKER``, which every
  ``atomic_directory`` output gets) or it is empty; never a file, the working folder or one of
  its ancestors (``merge --out "$PWD" --overwrite`` once deleted the user's files there).

``tempfile`` creates private folders (0700) and files (0600), which is right while a result is being
written; once it is complete it gets the modes an ordinary ``mkdir``/``open`` would have given it,
so a shared cluster's group can read exports and vectors as it reads any other file.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path

from capvector.errors import CapVectorError

Inputs = Sequence[str | Path | None]
"""The paths a command reads (``None`` entries, unset optional inputs, are skipped)."""

MARKER = ".capvector-output"
"""The file every folder ``atomic_directory`` writes holds: ``--overwrite`` replaces only those."""

_LEGACY = {"config.json": "capvector-export", "capability_vector.json": "capvector-vector"}
"""Outputs written before ``MARKER`` existed, known by the format their metadata declares."""

_FULL = (errno.ENOSPC, errno.EDQUOT)
# Writers in other languages lose the errno: safetensors (Rust) says "(os error 28)".
_FULL_TEXT = re.compile(r"No space left on device|Disk quota exceeded|os error (28|122)\b")


def check_writable(path: str | Path, what: str = "output", inside: bool = False) -> Path:
    """Fail before any work when ``path`` could not be created (``inside``: when files could not be
    created inside the folder ``path``): the nearest existing folder must be writable."""
    target = Path(path)
    ancestor = target.absolute() if inside else target.absolute().parent
    while not ancestor.exists():
        if ancestor.is_symlink():  # a link that leads nowhere: nothing can be made through it
            _refuse_broken_link(target, ancestor, what)
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


def _refuse_broken_link(target: Path, link: Path, what: str) -> None:
    try:
        os.stat(link)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise CapVectorError(
                f"cannot write {what} {target}: a symbolic link on its path points back into "
                f"itself ({exc.strerror}: {link}); fix the link or choose another folder"
            ) from None
    raise CapVectorError(
        f"cannot write {what} {target}: {link} is a symbolic link to {os.readlink(link)}, which "
        "does not exist; create that folder, fix the link or choose another folder"
    )


def check_output(
    path: str | Path,
    overwrite: bool,
    inputs: Inputs = (),
    what: str = "--out",
    folder: bool = False,
) -> Path:
    """Fail before any work when the output ``path`` is an input, holds one (replacing it would
    delete the input), lies inside one (it would add files to an input), exists without
    ``overwrite``, or could not be written. Paths are compared as real paths (links followed).

    ``folder``: the output is a folder written whole (``atomic_directory``) that replaces ``path``;
    then ``path`` may not be the working folder or hold it, and ``overwrite`` replaces only a
    folder capvector wrote or an empty one. Outputs that are written into rather than replaced (a
    report folder, a JSON file) pass ``overwrite=True``: their existing contents are no one's
    input to lose.
    """
    target = Path(path)
    real = check_outside_inputs(target, inputs, what)
    if folder:
        _refuse_working_folder(target, real, what)
    check_writable(target, what)
    _refuse_existing(target, overwrite, what)
    if folder and overwrite:
        _refuse_unless_ours(target, what)
    return target


def check_outside_inputs(
    path: str | Path, inputs: Inputs, what: str = "--out", may_hold: bool = False
) -> Path:
    """Fail when the output ``path`` is an input, lies inside one (it would add files to an
    input) or, unless ``may_hold`` (a folder written into, not replaced), holds one; its real path.
    """
    target = Path(path)
    real = _real_path(target, what)
    for source in inputs:
        if source is None:
            continue
        theirs = _real_path(Path(source), "input")
        if real == theirs:
            problem = "is an input"
        elif real in theirs.parents and not may_hold:
            problem = f"holds the input {source}"
        elif theirs in real.parents:
            problem = f"lies inside the input {source}"
        else:
            continue
        raise CapVectorError(
            f"{what} {target} {problem}; an output must be outside every input: choose another "
            f"{what}"
        )
    return real


@contextmanager
def atomic_directory(
    path: str | Path, overwrite: bool = False, inputs: Inputs = (), what: str = "--out"
) -> Iterator[Path]:
    """Yield a new temporary folder that becomes ``path`` only if the block succeeds.

    Checked like ``check_output``. The temporary folder lives beside the target so the final rename
    stays on one file system; its files are fsynced before it is renamed. Without ``overwrite`` the
    rename refuses a target that appeared meanwhile (nothing is moved aside); with it, the old
    target is replaced only once the new one is complete.
    """
    target = check_output(path, overwrite, inputs, what, folder=True)
    with _full_disk_is_an_error(target, what), _writer_lock(target, what):
        _refuse_existing(target, overwrite, what)  # a writer that held the lock may have made it
        if overwrite:
            _refuse_unless_ours(target, what)
        tmp = Path(tempfile.mkdtemp(prefix=_temporary_prefix(target), dir=target.parent))
        try:
            yield tmp
            (tmp / MARKER).write_text("written by capvector; --overwrite may replace this folder\n")
            _publish_modes(tmp)
            # On disk before the name points at it: a crash then leaves a whole result or none.
            for root, _dirs, files in os.walk(tmp):
                for name in [*files, "."]:
                    _fsync(Path(root) / name)
            _publish_directory(tmp, target, overwrite, what)
        except BaseException:
            _remove(tmp)
            raise
        _fsync(target.parent)


def _refuse_working_folder(target: Path, real: Path, what: str) -> None:
    cwd = Path(os.getcwd()).resolve()
    if real == cwd or real in cwd.parents:
        where = "is the working folder" if real == cwd else "holds the working folder"
        raise CapVectorError(
            f"{what} {target} {where}: an output folder replaces what is at its path, so it must "
            f"be a new folder; choose one, e.g. {what} {target / 'out'}"
        )


def _refuse_unless_ours(target: Path, what: str) -> None:
    """``--overwrite`` replaces a folder capvector wrote, or an empty one; nothing else."""
    if not os.path.lexists(target):
        return
    if target.is_symlink() or not target.is_dir():
        kind = "a symbolic link" if target.is_symlink() else "a file"
        raise CapVectorError(
            f"{what} {target} is {kind}, and this output is a folder: --overwrite replaces only a "
            f"folder capvector wrote; choose another {what}"
        )
    if (target / MARKER).is_file() or not any(target.iterdir()) or _legacy_output(target):
        return
    raise CapVectorError(
        f"{what} {target} is a folder capvector did not write (it has no {MARKER} file), so "
        f"--overwrite will not replace it: choose another {what} or empty it yourself"
    )


def _legacy_output(target: Path) -> bool:
    for name, fmt in _LEGACY.items():
        try:
            if json.loads((target / name).read_text()).get("format") == fmt:
                return True
        except (OSError, ValueError, AttributeError):
            continue
    return False


def disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or an error it was raised from) is a full disk or an exceeded quota."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno in _FULL:
            return True
        if _FULL_TEXT.search(str(seen)):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def no_room(
    path: str | Path, what: str = "output", exc: BaseException | None = None
) -> CapVectorError:
    """One line for a write that met a full disk: the path, the room left there, what to do."""
    path = Path(path)
    free = _free_bytes(path)
    room = "" if free is None else f" ({_size(free)} free once the partial output was removed)"
    quota = isinstance(exc, OSError) and exc.errno == errno.EDQUOT
    problem = "your disk quota ran out" if quota else "its disk filled up"
    return CapVectorError(
        f"cannot write {what} {path}: {problem} while writing it{room}; free space there or "
        f"choose another {what}"
    )


def check_room(path: str | Path, needed: int, what: str = "output") -> None:
    """Refuse before writing ``needed`` bytes at ``path`` when its disk has less room than that."""
    path = Path(path)
    free = _free_bytes(path)
    if free is not None and free < needed:
        raise CapVectorError(
            f"cannot write {what} {path}: it needs about {_size(needed)} and its disk has "
            f"{_size(free)} free; free space there or choose another {what}"
        )


def _free_bytes(path: Path) -> int | None:
    """Bytes an unprivileged writer may still use on the disk of ``path`` (its nearest existing
    ancestor); ``None`` where the file system does not say."""
    ancestor = path.absolute()
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    try:
        stat = os.statvfs(ancestor)
    except OSError:
        return None
    return stat.f_bavail * stat.f_frsize


def _size(n: int) -> str:
    """``1.9 MB``: decimal units, as ``df -H`` prints them."""
    if n < 1000:
        return f"{n} bytes"
    scaled = float(n)
    for unit in ("kB", "MB", "GB", "TB"):
        scaled /= 1000
        if scaled < 1000 or unit == "TB":
            break
    return f"{scaled:.1f} {unit}"


@contextmanager
def _full_disk_is_an_error(target: Path, what: str) -> Iterator[None]:
    """Around a writer (outermost: its temporary and lock are gone before this runs): a full
    disk is one line naming ``target``, whatever library met it."""
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        yield
    except CapVectorError:
        raise
    except Exception as exc:
        if disk_full(exc):
            raise no_room(target, what, exc) from exc
        raise


@contextmanager
def atomic_write_file(path: str | Path, what: str = "output") -> Iterator[Path]:
    """A temporary sibling file path (with the target's suffix, which some writers read the format
    from) that replaces ``path`` (fsynced, renamed) if the block succeeds. Files are results written
    again on each run: an existing one is replaced; the command checks its inputs with
    ``check_output`` before any work."""
    target = check_output(path, overwrite=True, what=what)
    if target.is_dir():
        raise CapVectorError(f"{what} {target} is a folder; give a file path")
    with _full_disk_is_an_error(target, what), _writer_lock(target, what):
        fd, name = tempfile.mkstemp(
            prefix=_temporary_prefix(target), suffix=target.suffix, dir=target.parent
        )
        os.close(fd)
        tmp = Path(name)
        try:
            yield tmp
            _fsync(tmp)
            _publish_modes(tmp)
            os.replace(tmp, target)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write a file through a temporary sibling and an atomic rename."""
    with atomic_write_file(path) as tmp:
        tmp.write_bytes(data)


def _real_path(path: Path, what: str) -> Path:
    """``path`` with every link resolved; a link loop is bad input, not a traceback."""
    try:
        return Path(os.path.realpath(path, strict=True))
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise CapVectorError(
                f"{what} {path} goes through a symbolic link that loops ({exc.filename}); remove "
                f"that link or choose another {what}"
            ) from None
    return Path(os.path.realpath(path))  # a path that does not exist yet


def _refuse_existing(target: Path, overwrite: bool, what: str) -> None:
    if not overwrite and os.path.lexists(target):
        raise CapVectorError(f"{target} exists; choose another {what} or pass --overwrite")


def _temporary_prefix(target: Path) -> str:
    """``.NAME.tmp-PID-``: the writer's pid tells the next writer whether it is still alive."""
    return f".{target.name}.tmp-{os.getpid()}-"


_TEMPORARY = re.compile(r"\.(?P<name>.+)\.tmp-(?P<pid>\d+)-\w+(?:\.\w+)?")
"""A temporary's file name: ``_temporary_prefix``, then mkstemp's random part and a suffix."""


@contextmanager
def _writer_lock(target: Path, what: str) -> Iterator[None]:
    """Hold ``.NAME.lock`` (flock) beside ``target`` while it is written: a second writer of the same
    output fails at once instead of racing the first to the rename. The kernel releases the lock
    when its holder dies however it dies, so a lock file left by ``kill -9`` does not block.

    While holding it, no other capvector process writes ``target``: temporaries of dead writers
    are removed here. A file system without locks (some NFS and Lustre mounts) writes unlocked and
    leaves temporaries alone (their pids may be another host's).
    """
    path = target.parent / f".{target.name}.lock"
    fd = _lock(path, target, what)
    if fd is None:
        yield
        return
    try:
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        _sweep_dead_writers(target)
        yield
    finally:
        path.unlink(missing_ok=True)  # before the lock is released: see ``_lock``
        os.close(fd)


def _lock(path: Path, target: Path, what: str) -> int | None:
    """The locked descriptor of ``path``; ``None`` where the file system has no locks."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 20).decode(errors="replace").strip()
            os.close(fd)
            pid = f" (pid {holder})" if holder.isdigit() else ""
            raise CapVectorError(
                f"another capvector process is writing {target}{pid}; wait for it to finish or "
                f"choose another {what}"
            ) from None
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                raise
            path.unlink(missing_ok=True)
            return None
        try:
            if os.path.samestat(os.fstat(fd), os.stat(path)):
                return fd
        except FileNotFoundError:
            pass
        # The holder before us removed the file as it released it: locking that removed file
        # guards nothing, so lock the one now at ``path``.
        os.close(fd)


def _sweep_dead_writers(target: Path) -> None:
    """Remove ``target``'s temporaries whose writer process no longer exists."""
    with os.scandir(target.parent) as entries:
        stale = [
            Path(e.path)
            for e in entries
            if (match := _TEMPORARY.fullmatch(e.name))
            and match["name"] == target.name
            and not _alive(int(match["pid"]))
        ]
    for path in stale:
        _remove(path)


def remove_writer_leftovers(directory: Path, pid: int) -> None:
    """Remove what process ``pid``'s writers hold in ``directory``: their temporaries and their
    lock files. For a process that ends on the spot (``os._exit``) instead of leaving its
    ``atomic_write_*`` blocks, which would have removed them."""
    with os.scandir(directory) as entries:
        temporaries = [
            e.path
            for e in entries
            if (match := _TEMPORARY.fullmatch(e.name)) and match["pid"] == str(pid)
        ]
    for path in temporaries:
        _remove(Path(path))
    for lock in directory.glob(".*.lock"):
        with suppress(OSError):
            if lock.read_text().strip() == str(pid):
                lock.unlink()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _publish_directory(tmp: Path, target: Path, overwrite: bool, what: str) -> None:
    if overwrite and os.path.lexists(target):
        # Named like our temporary, so if we die before removing it the next writer sweeps it.
        old = tmp.with_name(f"{tmp.name}_old")
        os.rename(target, old)
        try:
            os.rename(tmp, target)
        except BaseException:  # SIGTERM between the two renames included: put the old one back
            os.rename(old, target)
            raise
        _remove(old)
        return
    appeared = CapVectorError(
        f"{target} appeared while this command was writing it; it was left as it is and the "
        f"result discarded: choose another {what} or pass --overwrite"
    )
    if os.path.lexists(target):  # made after our check by a program that takes no lock
        raise appeared
    try:
        os.rename(tmp, target)  # fails on a file or a non-empty folder: never replaces one
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOTDIR):
            raise appeared from None
        raise


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


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
