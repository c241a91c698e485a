"""The websocket policy server: openpi's protocol, many clients, one batched forward at a time.

The protocol is openpi's ``src/openpi/serving/websocket_policy_server.py`` (the server its
``scripts/serve_policy.py`` runs, and the one ``openpi_client.WebsocketClientPolicy`` talks to):

1. On connect the server sends the policy's metadata (one msgpack map).
2. Each binary message is one observation; the answer is one msgpack map with ``actions``
   (T, A) float32 in the robot's raw units, ``policy_timing`` and ``server_timing`` (ms).
3. A text message instead of an answer is an error; openpi's client raises it as
   ``RuntimeError("Error in inference server:\\n<text>")``. openpi sends a traceback and closes
   the connection; we send one line naming the problem and keep the connection, so the client's
   next good request is answered (a bad observation is the client's, not the connection's).
4. ``GET /healthz`` answers ``OK`` (openpi's ``_health_check``).

openpi's handler calls the policy inline, on the event loop, so one forward holds up every
connection and none is batched. Here requests from all connections go into one queue; a batcher
takes what has arrived, waits up to ``batch_window`` for more (at most ``max_batch``), and runs
one forward in a worker thread, so the event loop keeps receiving and sending while the model
computes and the next batch collects meanwhile. Each connection awaits only its own answer: a
client that is slow to read blocks its own send, and the request of one that goes
away while it waits is cancelled before the forward.
"""

from __future__ import annotations

import asyncio
import http
import logging
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from websockets.asyncio.server import Request, Response, ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from capvector.serve.schema import IMAGES, Observation, ObservationError, ObservationSchema
from capvector.serve.wire import WireError, packb, unpackb

log = logging.getLogger(__name__)

MAX_MESSAGE = 64 * 2**20
"""Bytes in one request (openpi sets no limit); a bigger one closes the connection (1009)."""

ActBatch = Callable[[Sequence[Observation]], Sequence[np.ndarray]]
"""Observations in, one (T, A) chunk each out, in one forward (``VLAPolicy.act_batch``)."""


@dataclass
class _Pending:
    observation: Observation
    answer: asyncio.Future[tuple[np.ndarray, dict[str, float]]]
    shapes: tuple[tuple[int, ...], ...] = field(init=False)

    def __post_init__(self) -> None:
        # Requests batch with those whose images stack with theirs.
        self.shapes = tuple(image.shape for image in self.observation[IMAGES].values())


class PolicyFailed(RuntimeError):
    """The forward of a batch raised; every request in it gets this message."""


class PolicyServer:
    def __init__(
        self,
        act_batch: ActBatch,
        schema: ObservationSchema,
        metadata: Mapping[str, Any],
        *,
        max_batch: int = 16,
        batch_window: float = 0.002,
    ) -> None:
        """
        Args:
            act_batch: the policy (called in one worker thread, one batch at a time).
            schema: what a request must hold.
            metadata: sent to each client on connect.
            max_batch: most observations in one forward.
            batch_window: seconds the batcher waits for more requests after the first arrives.
        """
        self.act_batch = act_batch
        self.schema = schema
        self.metadata = dict(metadata)
        self.max_batch = max_batch
        self.batch_window = batch_window
        self._queue: asyncio.Queue[_Pending] | None = None

    async def run(self, sock: socket.socket, stop: asyncio.Event) -> None:
        """Serve on the bound ``sock`` until ``stop`` is set, then close every connection (1001,
        going away), finish the forward in flight and release the port."""
        self._queue = asyncio.Queue()
        with ThreadPoolExecutor(1, thread_name_prefix="capvector-serve-forward") as forward:
            batcher = asyncio.create_task(self._batch_forever(forward))
            try:
                async with serve(
                    self._connection, sock=sock, compression=None, max_size=MAX_MESSAGE,
                    process_request=_health_check,
                ):  # fmt: skip
                    stopped = asyncio.create_task(stop.wait())
                    # The batcher ends only by raising (a bug): stop serving then, not silently.
                    await asyncio.wait({stopped, batcher}, return_when=asyncio.FIRST_COMPLETED)
                    stopped.cancel()
                    if batcher.done():
                        batcher.result()
            finally:
                batcher.cancel()
                await asyncio.gather(batcher, return_exceptions=True)

    async def _connection(self, websocket: ServerConnection) -> None:
        peer = websocket.remote_address
        log.info("connection from %s opened", peer)
        try:
            await websocket.send(packb(self.metadata))
            previous_total: float | None = None
            async for message in websocket:
                start = time.monotonic()
                try:
                    answer = await self._answer(websocket, message)
                except (ObservationError, WireError, PolicyFailed) as err:
                    log.info("request from %s refused: %s", peer, err)
                    await websocket.send(str(err))
                    continue
                if answer is None:  # the client went away while its request waited
                    break
                answer["server_timing"] = {"infer_ms": (time.monotonic() - start) * 1000}
                if previous_total is not None:  # openpi's: the previous request's, send included
                    answer["server_timing"]["prev_total_ms"] = previous_total * 1000
                await websocket.send(packb(answer))
                previous_total = time.monotonic() - start
        except ConnectionClosed:
            pass
        log.info("connection from %s closed", peer)

    async def _answer(
        self, websocket: ServerConnection, message: str | bytes
    ) -> dict[str, Any] | None:
        """The answer to one request; ``None`` when the connection closed before it was ready
        (the request is then cancelled, and the batcher skips it)."""
        if isinstance(message, str):
            raise WireError("send observations as binary msgpack messages, not text")
        observation = self.schema.parse(unpackb(message))
        assert self._queue is not None
        pending = _Pending(observation, asyncio.get_running_loop().create_future())
        self._queue.put_nowait(pending)
        closed = asyncio.ensure_future(websocket.wait_closed())
        try:
            await asyncio.wait({pending.answer, closed}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            closed.cancel()
        if not pending.answer.done():
            pending.answer.cancel()
            return None
        actions, timing = pending.answer.result()
        return {"actions": actions, "policy_timing": timing}

    async def _batch_forever(self, forward: ThreadPoolExecutor) -> None:
        assert self._queue is not None
        loop = asyncio.get_running_loop()
        while True:
            batch = [await self._queue.get()]
            deadline = loop.time() + self.batch_window
            while len(batch) < self.max_batch:
                try:
                    timeout = deadline - loop.time()
                    batch.append(
                        self._queue.get_nowait()
                        if timeout <= 0 or not self._queue.empty()
                        else await asyncio.wait_for(self._queue.get(), timeout)
                    )
                except (asyncio.QueueEmpty, asyncio.TimeoutError):  # 3.10: not TimeoutError
                    break
            groups: dict[tuple[tuple[int, ...], ...], list[_Pending]] = {}
            for pending in batch:
                if not pending.answer.done():  # done: its client went away while it waited
                    groups.setdefault(pending.shapes, []).append(pending)
            for group in groups.values():
                await self._forward(forward, group)

    async def _forward(self, forward: ThreadPoolExecutor, group: list[_Pending]) -> None:
        loop = asyncio.get_running_loop()
        observations = [pending.observation for pending in group]
        start = time.monotonic()
        try:
            chunks = await loop.run_in_executor(forward, self.act_batch, observations)
        except Exception as err:  # the model's failure, not the clients': keep serving
            log.exception("the policy failed on a batch of %d", len(group))
            failed = PolicyFailed(
                f"the policy failed on a batch of {len(group)}: {type(err).__name__}: {err}"
            )
            for pending in group:
                if not pending.answer.done():
                    pending.answer.set_exception(failed)
            return
        timing = {"infer_ms": (time.monotonic() - start) * 1000, "batch_size": len(group)}
        for pending, chunk in zip(group, chunks, strict=True):
            if not pending.answer.done():  # done: its client went away during the forward
                pending.answer.set_result((np.asarray(chunk), timing))


def _health_check(connection: ServerConnection, request: Request) -> Response | None:
    # openpi's `_health_check`: load balancers and scripts poll it without the protocol.
    if request.path == "/healthz":
        return connection.respond(http.HTTPStatus.OK, "OK\n")
    return None
