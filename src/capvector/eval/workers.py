"""Worker processes that step robosuite simulators for batched evaluation.

The simulators' Python controllers (robosuite's OSC runs in Python on every 2 ms substep) cost
most of an evaluation; worker processes step several episodes on as many cores while the policy,
in the calling process, waits for their observations. A pool runs :class:`~capvector.eval.rollout.
Slots` in each worker, slot ``s`` on worker ``s % n``, and is kept for reuse across evaluations
(a worker starts in seconds: robosuite's import and its envs' compilation) until
:func:`capvector.eval.rollout.close_envs`. Workers are spawned, not forked, so no torch threads or
GL contexts of the parent are copied into them. The rollout hands its ``Slots`` class to the pool
(``worker_pool(n, Slots)``), so this module does not import the loop that imports it.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import traceback
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any, Protocol

__all__ = ["WorkerPool", "close_pools", "worker_pool"]


class Slots(Protocol):
    """What each worker runs: :class:`capvector.eval.rollout.Slots`."""

    def handle(self, commands: Sequence[tuple[int, str, Any]]) -> list[tuple[int, Any]]: ...

    def close(self) -> None: ...


def _serve(connection: Connection, make_slots: Callable[[], Slots]) -> None:
    slots = make_slots()
    try:
        while (commands := connection.recv()) is not None:
            try:
                connection.send(("ok", slots.handle(commands)))
            except Exception:
                connection.send(("error", traceback.format_exc()))
    except (EOFError, KeyboardInterrupt):
        pass  # the parent went away
    finally:
        slots.close()


class WorkerPool:
    """``workers`` processes each running ``make_slots()``; :meth:`handle` as ``Slots.handle``."""

    def __init__(self, workers: int, make_slots: Callable[[], Slots]) -> None:
        if workers < 1:
            raise ValueError(f"a worker pool needs at least 1 worker, got {workers}")
        self.make_slots = make_slots
        context = mp.get_context("spawn")
        self._connections: list[Connection] = []
        self._processes = []
        for i in range(workers):
            ours, theirs = context.Pipe()
            process = context.Process(
                target=_serve, args=(theirs, make_slots), name=f"capvector-sim-{i}", daemon=True
            )
            process.start()
            theirs.close()
            self._connections.append(ours)
            self._processes.append(process)

    def __len__(self) -> int:
        return len(self._processes)

    def handle(self, commands: Sequence[tuple[int, str, Any]]) -> list[tuple[int, Any]]:
        """Each worker gets its slots' commands at once; all step in parallel."""
        by_worker: dict[int, list[tuple[int, str, Any]]] = {}
        for command in commands:
            by_worker.setdefault(command[0] % len(self), []).append(command)
        for worker, batch in by_worker.items():
            self._connections[worker].send(batch)
        replies: list[tuple[int, Any]] = []
        errors = []
        for worker in by_worker:
            try:
                status, payload = self._connections[worker].recv()
            except EOFError:
                status, payload = (
                    "error",
                    f"worker {worker} died (exit code {self._processes[worker].exitcode})",
                )
            if status == "ok":
                replies += payload
            else:
                errors.append(payload)
        if errors:
            self.close()  # its episodes' state is lost: the next evaluation starts a fresh pool
            raise RuntimeError("a simulator worker failed:\n" + "\n".join(errors))
        return replies

    def close(self) -> None:
        for connection in self._connections:
            with contextlib.suppress(BrokenPipeError, OSError):
                connection.send(None)
        for process in self._processes:
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
        for connection in self._connections:
            connection.close()
        self._connections, self._processes = [], []
        _pools.pop(id(self), None)


_pools: dict[int, WorkerPool] = {}


def worker_pool(workers: int, make_slots: Callable[[], Slots]) -> WorkerPool:
    """A running pool of ``workers`` processes, reused across evaluations."""
    for pool in _pools.values():
        if len(pool) == workers and pool.make_slots is make_slots:
            return pool
    close_pools()
    pool = WorkerPool(workers, make_slots)
    _pools[id(pool)] = pool
    return pool


def close_pools() -> None:
    for pool in list(_pools.values()):
        pool.close()
