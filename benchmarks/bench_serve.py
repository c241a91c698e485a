"""Serving cost: round-trip latency per chunk through ``capvector serve`` against a direct
in-process forward of the same policy, and throughput with 1, 4 and 16 concurrent clients.

    python benchmarks/bench_serve.py [--requests 50] [--image-size 224] [--clients 1 4 16]

The policy is the untrained tiny OpenVLA-OFT preset (deterministic, so every answer can be
checked) in an export folder; the server is the real ``capvector serve`` in its own process on
loopback, the clients are openpi-client's ``WebsocketClientPolicy`` in threads of this one,
sending what openpi's LIBERO example sends (two 224 px uint8 images, an 8-d state, a prompt).
Baseline, in this run: ``VLAPolicy.act_batch`` on one observation at a time in this process, the
mean of a run before and one after the served ones. Every served answer is checked against it.
The machine is shared: the 1-minute load average is printed with the tables.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
from openpi_client.websocket_client_policy import WebsocketClientPolicy

from capvector.data.spec import DataSpec
from capvector.data.statistics import compute_statistics
from capvector.module import VLAModule, load_module
from capvector.policy import VLAPolicy
from capvector.serve.schema import ObservationSchema

LISTENING = re.compile(r"listening on ws://([\d.]+):(\d+)")
PRESET = "openvla-oft-tiny"


def make_export(folder: Path) -> Path:
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    statistics = compute_statistics(rng.normal(size=(100, 7)), rng.normal(size=(100, 8)), 4)
    spec = DataSpec(statistics={"capvector": statistics})
    return VLAModule(backbone=PRESET, data_spec=spec).export(folder / "export")


def observation(seed: int, size: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    return {
        "observation/image": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
        "observation/wrist_image": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
        "observation/state": rng.normal(size=8),
        "prompt": "put the bowl on the plate",
    }


def start_server(export: Path, folder: Path) -> tuple[subprocess.Popen, str, int]:
    out = folder / "serve.out"
    with out.open("w") as stdout:
        process = subprocess.Popen(
            [sys.executable, "-m", "capvector.cli", "serve", "--ckpt", str(export), "--port", "0",
             "--device", "cpu"],
            stdout=stdout, stderr=subprocess.DEVNULL,
        )  # fmt: skip
    while (found := LISTENING.search(out.read_text())) is None:
        if process.poll() is not None:
            raise SystemExit("capvector serve did not start")
        time.sleep(0.1)
    return process, found.group(1), int(found.group(2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=50, help="per client")
    parser.add_argument("--image-size", type=int, default=224)
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 4, 16])
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    with tempfile.TemporaryDirectory() as tmp:
        export = make_export(Path(tmp))
        module = load_module(export).eval()
        policy = VLAPolicy(module.backbone, module.data_spec)
        schema = ObservationSchema.of(module.data_spec)
        total = max(args.clients) * args.requests
        requests = [observation(seed, args.image_size) for seed in range(total)]
        parsed = [schema.parse(r) for r in requests]

        def one_at_a_time() -> tuple[float, list[np.ndarray]]:
            start = time.perf_counter()
            chunks = [policy.act_batch([p])[0] for p in parsed[: args.requests]]
            return (time.perf_counter() - start) / args.requests, chunks

        policy.act_batch(parsed[:1])  # warm-up, as the server's
        before, expected = one_at_a_time()
        for i in range(args.requests, total, 16):
            expected += policy.act_batch(parsed[i : i + 16])
        process, host, port = start_server(export, Path(tmp))
        try:
            rows = [
                run_clients(host, port, n, args.requests, requests, expected) for n in args.clients
            ]
        finally:
            process.terminate()
            process.wait(timeout=60)
        # The machine is shared: the baseline is the mean of one run before and one after.
        direct = (before + one_at_a_time()[0]) / 2

    one = rows[0]
    print(
        f"{PRESET}, 2 cameras at {args.image_size} px, chunks of {module.data_spec.chunk_size}, "
        f"{args.requests} requests per client, {os.cpu_count()} cores, "
        f"{torch.get_num_threads()} torch thread(s) per process"
    )
    ms = {
        "direct in-process forward (`VLAPolicy.act_batch`, 1 observation)": direct * 1000,
        "served: the forward inside the server (`policy_timing.infer_ms`)": one["forward_ms"],
        "served: round trip, 1 client (`WebsocketClientPolicy.infer`)": one["latency_ms"],
    }
    table(
        ["path", "ms per chunk", "× direct forward"],
        [[path, f"{t:.1f}", f"{t / 1000 / direct:.2f}"] for path, t in ms.items()],
    )
    table(
        ["clients", "chunks/s", "× direct forward, one at a time", "mean round trip ms",
         "mean batch"],
        [[str(r["clients"]), f"{r['rate']:.1f}", f"{r['rate'] * direct:.2f}",
          f"{r['latency_ms']:.1f}", f"{r['batch']:.1f}"] for r in rows],
    )  # fmt: skip
    print(f"\nload average (1 min) after the run: {os.getloadavg()[0]:.2f}")


def table(header: list[str], rows: list[list[str]]) -> None:
    print("\n| " + " | ".join(header) + " |\n|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(row) + " |")


def run_clients(
    host: str, port: int, clients: int, per_client: int, requests: list, expected: list
) -> dict[str, float]:
    """``clients`` threads, each with its own connection, ``per_client`` requests each."""
    barrier = threading.Barrier(clients + 1)

    def client(index: int) -> list[tuple[float, float, int]]:
        policy = WebsocketClientPolicy(host, port)
        barrier.wait()
        timings = []
        for i in range(index * per_client, (index + 1) * per_client):
            sent = time.perf_counter()
            answer = policy.infer(requests[i])
            timings.append((time.perf_counter() - sent, answer["policy_timing"]["infer_ms"],
                            answer["policy_timing"]["batch_size"]))  # fmt: skip
            np.testing.assert_allclose(answer["actions"], expected[i], rtol=1e-5, atol=1e-5)
        return timings

    with ThreadPoolExecutor(clients) as pool:
        futures = [pool.submit(client, i) for i in range(clients)]
        barrier.wait()
        start = time.perf_counter()
        timings = [t for f in futures for t in f.result()]
        elapsed = time.perf_counter() - start
    latency, forward, batch = (np.mean(column) for column in zip(*timings, strict=True))
    return {
        "clients": clients, "rate": len(timings) / elapsed, "latency_ms": latency * 1000,
        "forward_ms": forward, "batch": batch,
    }  # fmt: skip


if __name__ == "__main__":
    main()
