"""``capvector serve``: load a policy once and answer observations over openpi's websocket protocol
until SIGINT or SIGTERM."""

from __future__ import annotations

import asyncio
import errno
import logging
import signal
import socket
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch

from capvector.errors import CapVectorError
from capvector.eval.device import Precision, resolve_device, resolve_precision
from capvector.module import load_for_inference
from capvector.policy import VLAPolicy
from capvector.serve.schema import (
    IMAGES,
    INSTRUCTION,
    MAX_ASPECT,
    MAX_IMAGE_PIXELS,
    MAX_PROMPT_TOKENS,
    PROPRIO,
    Observation,
    ObservationSchema,
)
from capvector.serve.server import PolicyServer
from capvector.tool_cli import run_tool


class ServedPolicy:
    """A checkpoint or export loaded once as ``capvector evaluate`` loads it (``load_for_inference`` +
    ``VLAPolicy``: statistics, cameras, crop and tokenizer from the export), on ``device``, each
    forward under ``precision``."""

    def __init__(self, ckpt: str, device: torch.device, precision: Precision) -> None:
        self.precision = precision
        # Under autocast a bf16 export is served in bf16 (no float32 copy).
        backbone, self.spec = load_for_inference(ckpt, keep_dtype=precision != "32-true")
        backbone.to(device)
        self.tokenizer = backbone.tokenizer
        self.policy = VLAPolicy(backbone, self.spec, precision)
        self.device = device
        self.describe = {
            "family": backbone.config_class.family,
            "preset": backbone.config.preset,
        }

    def act_batch(self, observations: Sequence[Observation]) -> list[np.ndarray]:
        return self.policy.act_batch(observations)

    def count_tokens(self, prompt: str) -> int:
        """The instruction's tokens as the backbone tokenizes it (characters without one)."""
        if self.tokenizer is None:
            return len(prompt)
        return len(self.tokenizer(prompt, add_special_tokens=False, verbose=False)["input_ids"])

    def warm_up(self) -> None:
        """One forward before the first client: a device or dtype problem, or weights that answer
        NaN, show at start."""
        size = self.spec.image_size
        image = np.zeros((size, size, 3), np.uint8)
        (chunk,) = self.act_batch([{
            IMAGES: {camera: image for camera in self.spec.cameras},
            PROPRIO: np.zeros(self.spec.proprio_dim, np.float32),
            INSTRUCTION: "",
        }])  # fmt: skip
        if not np.isfinite(chunk).all():
            raise CapVectorError(
                "the policy answers a blank observation with non-finite actions "
                f"({int((~np.isfinite(chunk)).sum())} of {chunk.size}): its weights hold NaN or "
                "inf, or its inputs overflow; serve another checkpoint"
            )

    def metadata(self, schema: ObservationSchema, max_batch: int) -> dict[str, Any]:
        """What each client receives on connect (openpi's ``policy.metadata``)."""
        from importlib.metadata import version

        spec = self.spec
        return {
            "server": "capvector",
            "capvector_version": version("capvector"),
            **self.describe,
            "cameras": list(spec.cameras),
            "image_size": spec.image_size,
            # The cameras' vertical field of view it trained at (None: the scene's own), so a
            # client whose scene has fixed cameras (LIBERO) can refuse a policy of other views.
            "camera_fovy": spec.camera_fovy,
            "proprio_dim": spec.proprio_dim,
            "action_dim": spec.action_dim,
            "action_horizon": spec.chunk_size,
            "openpi_keys": schema.key_map(),
            "device": str(self.device),
            "precision": self.precision,
            "max_batch": max_batch,
            "max_image_pixels": schema.max_image_pixels,
            "max_aspect": schema.max_aspect,
            "max_prompt_tokens": schema.max_prompt_tokens,
        }


def serve(
    ckpt: str,
    *,
    device: str | None = None,
    precision: Precision | None = None,
    host: str = "127.0.0.1",
    port: int = 8000,
    max_batch: int = 16,
    batch_window_ms: float = 2.0,
    default_prompt: str | None = None,
    max_connections: int = 64,
    idle_timeout_s: float = 300.0,
    max_image_pixels: int = MAX_IMAGE_PIXELS,
    max_aspect: float = MAX_ASPECT,
    max_prompt_tokens: int = MAX_PROMPT_TOKENS,
) -> int:
    """Answer observations with action chunks over openpi's websocket protocol.

    ``openpi_client.WebsocketClientPolicy`` talks to it. SIGINT or SIGTERM closes every
    connection, releases the port and returns 0.

    Args:
        ckpt: Lightning checkpoint or export folder.
        device: where the model runs, e.g. cpu, cuda, cuda:1 (default: cuda when there is one).
        precision: 32-true, or bf16-mixed / 16-mixed (autocast; 16-mixed needs a GPU); default
            bf16-mixed on a GPU, 32-true elsewhere.
        host: address to listen on (0.0.0.0: every interface).
        port: port to listen on (0: one the system picks, printed at start).
        max_batch: most observations in one forward.
        batch_window_ms: how long a request waits for others to share its forward.
        default_prompt: the instruction of requests that send none.
        max_connections: most connections open at once; one more is closed (1013, try later).
        idle_timeout_s: a connection without a request for this long is closed (0: never).
        max_image_pixels: most pixels (H x W) in one image of a request.
        max_aspect: most long side over short side of an image.
        max_prompt_tokens: most tokens in an instruction.
    """
    for name, value, low in (
        ("--max-batch", max_batch, 1), ("--batch-window-ms", batch_window_ms, 0),
        ("--max-connections", max_connections, 1), ("--idle-timeout-s", idle_timeout_s, 0),
        ("--max-image-pixels", max_image_pixels, 1), ("--max-aspect", max_aspect, 1),
        ("--max-prompt-tokens", max_prompt_tokens, 1),
    ):  # fmt: skip
        if not value >= low:  # NaN too
            raise CapVectorError(f"{name} must be >= {low}, got {value}")
    torch_device = resolve_device(device)
    precision = resolve_precision(torch_device, precision)  # refused before the load
    with _bound(host, port) as sock:  # a taken port fails before minutes of loading
        policy = ServedPolicy(ckpt, torch_device, precision)
        policy.warm_up()
        schema = ObservationSchema.of(
            policy.spec, default_prompt, max_image_pixels=max_image_pixels,
            max_aspect=max_aspect, max_prompt_tokens=max_prompt_tokens,
            count_tokens=policy.count_tokens,
        )  # fmt: skip
        metadata = policy.metadata(schema, max_batch)
        server = PolicyServer(
            policy.act_batch, schema, metadata, max_batch=max_batch,
            batch_window=batch_window_ms / 1000, idle_timeout=idle_timeout_s or None,
            max_connections=max_connections,
        )  # fmt: skip
        address = sock.getsockname()
        print(
            f"capvector serve: {metadata['preset']} from {ckpt} on {torch_device} ({precision}), "
            f"cameras {', '.join(policy.spec.cameras)}, chunks of {policy.spec.chunk_size}; "
            f"listening on ws://{address[0]}:{address[1]}",
            flush=True,
        )
        received = asyncio.run(_serve_until_signal(server, sock))
    print(f"capvector serve: stopped ({received})", file=sys.stderr, flush=True)
    return 0


@contextmanager
def _bound(host: str, port: int) -> Iterator[socket.socket]:
    if not 0 <= port <= 65535:
        raise CapVectorError(f"--port {port} is not a port (0-65535)")
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
        sock = socket.create_server((host, port), family=family)
    except socket.gaierror as err:
        raise CapVectorError(f"--host {host}: {err.strerror}") from err
    except OSError as err:
        if err.errno == errno.EADDRINUSE:
            raise CapVectorError(
                f"port {port} on {host} is in use (another server?); pass another --port"
            ) from err
        raise
    with sock:
        yield sock


async def _serve_until_signal(server: PolicyServer, sock: socket.socket) -> str:
    """Serve until SIGINT or SIGTERM, whose name is returned: a long-running server stops
    cleanly on either instead of dying mid-send (the CLI's own SIGTERM handler would raise
    wherever the event loop happens to be)."""
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    received: list[str] = []
    handled = (signal.SIGINT, signal.SIGTERM)

    def on_signal(signum: signal.Signals) -> None:
        received.append(signum.name)
        stop.set()

    for signum in handled:
        loop.add_signal_handler(signum, on_signal, signum)
    try:
        await server.run(sock, stop)
    finally:
        for signum in handled:
            loop.remove_signal_handler(signum)
    return received[0]


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="capvector serve: %(message)s")
    logging.getLogger("websockets").setLevel(logging.WARNING)
    return run_tool(serve, argv, "serve")
