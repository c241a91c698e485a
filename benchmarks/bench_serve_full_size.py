"""A full-size export served: ``capvector serve`` of it answers openpi-client's
``WebsocketClientPolicy``; the server's load time and peak RSS, the first answer's and the steady
answers' latency.

    python benchmarks/bench_serve_full_size.py --ckpt EXPORT [--requests 5] [--out FILE]

The server is the real ``capvector serve --device cpu --precision bf16-mixed`` in its own process
on loopback (a bf16 export stays bf16: ``module.load_for_inference``); the client sends what
openpi's LIBERO example sends (two 224 px uint8 images, an 8-d state, a prompt), one request at a
time. The server's peak RSS is the kernel's (``os.wait4`` after SIGTERM), so it includes the load.
Results go to ``--out`` (JSON, written atomically) and stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_serve import LISTENING, observation  # noqa: E402


def serve(export: Path, folder: Path, threads: int) -> tuple[subprocess.Popen, str, int, float]:
    """The server, its address and the seconds until it listened (the load and a warm-up)."""
    out = folder / "serve.out"
    start = time.perf_counter()
    with out.open("w") as stdout:
        process = subprocess.Popen(
            [sys.executable, "-m", "capvector.cli", "serve", "--ckpt", str(export), "--port", "0",
             "--device", "cpu", "--precision", "bf16-mixed"],
            stdout=stdout, stderr=subprocess.STDOUT,
            env={**os.environ, "OMP_NUM_THREADS": str(threads)},
        )  # fmt: skip
    while (found := LISTENING.search(out.read_text())) is None:
        if process.poll() is not None:
            raise SystemExit(f"capvector serve did not start:\n{out.read_text()[-3000:]}")
        time.sleep(0.5)
    return process, found.group(1), int(found.group(2)), time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", type=Path, required=True, help="a full-size export folder")
    parser.add_argument("--requests", type=int, default=5, help="after the first")
    parser.add_argument("--threads", type=int, default=2, help="the server's OMP_NUM_THREADS")
    parser.add_argument("--out", type=Path, help="JSON file for the row")
    args = parser.parse_args()
    from openpi_client.websocket_client_policy import WebsocketClientPolicy

    with tempfile.TemporaryDirectory() as tmp:
        process, host, port, load_seconds = serve(args.ckpt, Path(tmp), args.threads)
        try:
            client = WebsocketClientPolicy(host, port)
            metadata = client.get_server_metadata()
            size = int(metadata.get("image_size", 224))
            seconds: list[float] = []
            shapes: set[tuple[int, ...]] = set()
            finite = True
            for i in range(1 + args.requests):
                start = time.perf_counter()
                actions = np.asarray(client.infer(observation(i, size))["actions"])
                seconds.append(time.perf_counter() - start)
                shapes.add(actions.shape)
                finite &= bool(np.isfinite(actions).all())
        finally:
            process.send_signal(signal.SIGTERM)
            _, status, usage = os.wait4(process.pid, 0)
    row: dict[str, Any] = {
        "ckpt": str(args.ckpt),
        "preset": metadata.get("preset"),
        "server_start_seconds": load_seconds,
        "first_answer_seconds": seconds[0],
        "steady_answer_seconds": seconds[1:],
        "steady_median_seconds": statistics.median(seconds[1:]) if args.requests else None,
        "actions_shapes": sorted(shapes),
        "finite": finite,
        "server_peak_rss_gib": usage.ru_maxrss * 1024 / 1024**3,
        "server_exit_status": status,
        "server_threads": args.threads,
        "load_average": os.getloadavg()[0],
        "command": "python benchmarks/bench_serve_full_size.py --ckpt EXPORT "
        f"--requests {args.requests} --threads {args.threads}",
    }
    print(json.dumps(row))
    if args.out is not None:
        tmp = args.out.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(row, indent=2) + "\n")
        tmp.replace(args.out)


if __name__ == "__main__":
    main()
