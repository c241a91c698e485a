"""Torch threads for a fit started by hand: its share of the CPUs beside the other fits running.

Torch takes one thread per core. Two fits started by hand on a 2-core machine then run four busy
threads on two cores, and each runs several times slower than with one thread each (OpenMP threads
wait for each other at every parallel region; ``docs/performance.md`` has the numbers). A fit holds
an exclusive ``flock`` on a file in a registry folder while it runs; the fits running are the files
whose lock is held (a lock dies with its process, so a killed fit is not counted), and each takes
``usable_cpus() // fits`` threads. The registry is per user, in the temporary directory.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path

from capvector.io.cpus import usable_cpus

REGISTRY = Path(tempfile.gettempdir()) / f"capvector-{os.getuid()}" / "fits"


class RunningFit:
    """This process's entry in the registry, from ``open`` to ``close``."""

    def __init__(self, registry: Path = REGISTRY) -> None:
        self.registry = registry
        self._file: int | None = None

    def open(self) -> RunningFit:
        self.registry.mkdir(parents=True, exist_ok=True)
        # Locked before it is named *.lock: a counter must never find it unlocked and remove it.
        draft = self.registry / f"{os.getpid()}.draft"
        self._file = os.open(draft, os.O_CREAT | os.O_RDWR, 0o600)
        fcntl.flock(self._file, fcntl.LOCK_EX)
        draft.rename(self.registry / f"{os.getpid()}.lock")
        return self

    def close(self) -> None:
        if self._file is not None:
            (self.registry / f"{os.getpid()}.lock").unlink(missing_ok=True)
            os.close(self._file)  # releases the lock
            self._file = None


def running_fits(registry: Path = REGISTRY) -> int:
    """The fits whose entry is locked; entries left by ended processes are removed."""
    count = 0
    for path in registry.glob("*.lock") if registry.is_dir() else []:
        try:
            handle = os.open(path, os.O_RDWR)
        except FileNotFoundError:  # its fit just ended
            continue
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            count += 1
        else:
            path.unlink(missing_ok=True)
        finally:
            os.close(handle)
    return count


def fair_threads(registry: Path = REGISTRY) -> int:
    """This process's share of its usable CPUs among the fits running (itself included)."""
    return max(1, usable_cpus() // max(1, running_fits(registry)))
