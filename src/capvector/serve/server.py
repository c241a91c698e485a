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

One client cannot starve or break the others: the schema bounds what one request may cost
(image pixels and aspect, prompt tokens) before it is queued; a batch whose forward raises is
answered again one request at a time, so only the request that fails gets the error; a chunk
with a NaN or inf is never sent (its client gets an error, the server logs it and goes on); a
connection idle for ``idle_timeout`` seconds is closed, and beyond ``max_connections`` a new one
is closed at once (1013, try again later).
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
from websockets.frames import CloseCode

from capvector.serve.schema import IMAGES, Observation, ObservationError, ObservationSchema
from capvector.serve.wire import WireError, packb, unpackb

log = logging.getLogger(__name__)


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
    """The policy raised on a request, or answered it with a non-finite chunk; its client gets
    this message (and only its client)."""


class PolicyServer:
    def __init__(
        self,
        act_batch: ActBatch,
        schema: ObservationSchema,
        metadata: Mapping[str, Any],
        *,
        max_batch: int = 16,
        batch_window: float = 0.002,
        idle_timeout: float | None = 300.0,
        max_connections: int = 64,
        keepalive: float | None = 20.0,
    ) -> None:
        """
        Args:
            act_batch: the policy (called in one worker thread, one batch at a time).
            schema: what a request must hold.
            metadata: sent to each client on connect.
            max_batch: most observations in one forward.
            batch_window: seconds the batcher waits for more requests after the first arrives.
            idle_timeout: seconds a connection may go without a request before it is closed
                (None: never).
            max_connections: most connections open at once; one more is closed on opening.
            keepalive: seconds between pings, and to wait for their answer, before a silent
                connection is closed (websockets' default 20; None: no pings). A client that
                steps a simulator on a loaded machine may not answer in time between requests.
        """
        self.act_batch = act_batch
        self.schema = schema
        self.metadata = dict(metadata)
        self.max_batch = max_batch
        self.batch_window = batch_window
        self.idle_timeout = idle_timeout
        self.max_connections = max_connections
        self.keepalive = keepalive
        self._open = 0
        self._queue: asyncio.Queue[_Pending] | None = None

    async def run(self, sock: socket.socket, stop: asyncio.Event) -> None:
        """Serve on the bound ``sock`` until ``stop`` is set, then close every connection (1001,
        going away), finish the forward in flight and release the port."""
        self._queue = asyncio.Queue()
        with ThreadPoolExecutor(1, thread_name_prefix="capvector-serve-forward") as forward:
            batcher = asyncio.create_task(self._batch_forever(forward))
            try:
                async with serve(
                    self._connection, sock=sock, compression=None, max_size=self.schema.max_message_bytes,
                    process_request=_health_check, ping_interval=self.keepalive,
                    ping_timeout=self.keepalive,
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
        if self._open >= self.max_connections:
            log.warning("connection from %s refused: %d open already", peer, self._open)
            await websocket.close(
                CloseCode.TRY_AGAIN_LATER,
                f"the server holds its cap of {self.max_connections} connections; try again later",
            )
            return
        self._open += 1
        log.info("connection from %s opened", peer)
        try:
            await self._converse(websocket, peer)
        except ConnectionClosed:
            pass
        finally:
            self._open -= 1
        log.info("connection from %s closed", peer)

    async def _converse(self, websocket: ServerConnection, peer: Any) -> None:
        await websocket.send(packb(self.metadata))
        previous_total: float | None = None
        while True:
            try:  # cancelling recv is safe (websockets' docs): no message is lost
                message = await asyncio.wait_for(websocket.recv(), self.idle_timeout)
            except asyncio.TimeoutError:  # 3.10: not TimeoutError
                log.info("connection from %s idle for %s s: closed", peer, self.idle_timeout)
                await websocket.close(
                    CloseCode.NORMAL_CLOSURE, f"idle for {self.idle_timeout:g} s; reconnect"
                )
                return
            start = time.monotonic()
            try:
                answer = await self._answer(websocket, message)
            except (ObservationError, WireError, PolicyFailed) as err:
                log.info("request from %s refused: %s", peer, err)
                await websocket.send(str(err))
                continue
            if answer is None:  # the client went away while its request waited
                return
            answer["server_timing"] = {"infer_ms": (time.monotonic() - start) * 1000}
            if previous_total is not None:  # openpi's: the previous request's, send included
                answer["server_timing"]["prev_total_ms"] = previous_total * 1000
            await websocket.send(packb(answer))
            previous_total = time.monotonic() - start

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
            if len(group) > 1:
                # One request can fail a batch (e.g. memory for its size): answer each alone, so
                # only that one's client gets an error and a bystander its actions.
                log.warning(
                    "the policy failed on a batch of %d (%s: %s); answering each alone",
                    len(group), type(err).__name__, err,
                )  # fmt: skip
                for pending in group:
                    if not pending.answer.done():
                        await self._forward(forward, [pending])
                return
            log.exception("the policy failed on a request")
            _fail(group[0], f"the policy failed on this request: {type(err).__name__}: {err}")
            return
        timing = {"infer_ms": (time.monotonic() - start) * 1000, "batch_size": len(group)}
        for pending, chunk in zip(group, chunks, strict=True):
            chunk = np.asarray(chunk)
            if not np.isfinite(chunk).all():  # a robot must never receive one
                bad = int(np.size(chunk) - np.isfinite(chunk).sum())
                log.error("the policy's actions hold %d non-finite values; not sent", bad)
                _fail(
                    pending,
                    f"the policy's actions for this observation hold {bad} non-finite values of "
                    f"{chunk.size} (NaN or inf); not sent: do not act on this step",
                )
            elif not pending.answer.done():  # done: its client went away during the forward
                pending.answer.set_result((chunk, timing))


def _fail(pending: _Pending, message: str) -> None:
    if not pending.answer.done():
        pending.answer.set_exception(PolicyFailed(message))


def _health_check(connection: ServerConnection, request: Request) -> Response | None:
    # openpi's `_health_check`: load balancers and scripts poll it without the protocol.
    if request.path == "/healthz":
        return connection.respond(http.HTTPStatus.OK, "OK\n")
    return None
