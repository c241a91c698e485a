"""``capvector serve`` driven by openpi's own client (``openpi-client``, a test dependency): the
actions equal the in-process policy's, malformed observations get an error naming the problem and
the server goes on, 16 clients x 50 requests get their own answers, and signals stop it cleanly.

The server is the real command in a subprocess on loopback (port 0: the system picks one)."""

from __future__ import annotations

import asyncio
import os
import re
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import websockets.sync.client
from openpi_client import msgpack_numpy
from openpi_client.action_chunk_broker import ActionChunkBroker
from openpi_client.websocket_client_policy import WebsocketClientPolicy
from safetensors.torch import load_file, save_file

from capvector.cli import main
from capvector.data.spec import DataSpec
from capvector.data.statistics import compute_statistics
from capvector.module import VLAModule, load_module
from capvector.policy import VLAPolicy
from capvector.serve.schema import ObservationError, ObservationSchema
from capvector.serve.server import PolicyServer
from capvector.serve.wire import WireError, packb, unpackb
from capvector.workflows.serve import ServedPolicy

CAMERAS = ["agentview", "robot0_eye_in_hand"]
SIZE = 64
START_TIMEOUT = 180  # seconds: importing torch and loading on a busy 2-core machine
LISTENING = re.compile(r"listening on ws://([\d.]+):(\d+)")

# openpi-client 0.1.2 connects without a context manager, which websockets 14+ deprecates.
pytestmark = pytest.mark.filterwarnings(
    "ignore:connect\\(\\) must be used as a context manager:DeprecationWarning"
)


@pytest.fixture(scope="module")
def export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny OpenVLA-OFT export with its own statistics (q01/q99 of random data)."""
    rng = np.random.default_rng(0)
    stats = compute_statistics(rng.normal(size=(200, 7)), rng.normal(size=(200, 8)), 4)
    spec = DataSpec(cameras=CAMERAS, image_size=SIZE, statistics={"capvector": stats})
    torch.manual_seed(0)
    return VLAModule(backbone="openvla-oft-tiny", data_spec=spec).export(
        tmp_path_factory.mktemp("serve") / "export"
    )


@pytest.fixture(scope="module")
def reference(export: Path) -> VLAPolicy:
    """The policy as ``capvector evaluate`` loads it, in this process."""
    module = load_module(export).eval()
    return VLAPolicy(module.backbone, module.data_spec)


@dataclass
class Server:
    process: subprocess.Popen
    host: str
    port: int
    stderr: Path

    def client(self) -> WebsocketClientPolicy:
        return WebsocketClientPolicy(self.host, self.port)

    def stop(self, signum: int = signal.SIGTERM) -> tuple[int, str]:
        self.process.send_signal(signum)
        code = self.process.wait(timeout=60)
        return code, self.stderr.read_text()


def start_server(
    export: Path, folder: Path, *args: str, address_space: int | None = None
) -> Server:
    """``capvector serve`` on a free loopback port, with ``args``; returns once it listens.
    ``address_space``: bytes of virtual memory the server may map (an allocation beyond fails
    at once instead of swapping the shared machine)."""
    out, err = folder / "stdout.txt", folder / "stderr.txt"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "capvector.cli", "serve", "--ckpt", str(export), "--port", "0"]

    def limit() -> None:
        if address_space is not None:
            resource.setrlimit(resource.RLIMIT_AS, (address_space, address_space))

    with out.open("w") as stdout, err.open("w") as stderr:
        process = subprocess.Popen(
            [*command, *args], stdout=stdout, stderr=stderr, env=env, preexec_fn=limit
        )
    deadline = time.monotonic() + START_TIMEOUT
    while (found := LISTENING.search(out.read_text())) is None:
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            pytest.fail(f"capvector serve did not start: {err.read_text()[-3000:]}")
        time.sleep(0.1)
    return Server(process, found.group(1), int(found.group(2)), err)


@pytest.fixture(scope="module")
def server(export: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    # The tests leave their clients connected: more than the default cap of 64 over the module.
    running = start_server(export, tmp_path_factory.mktemp("server"), "--max-connections", "512")
    try:
        yield running
    finally:
        if running.process.poll() is None:
            code, stderr = running.stop()
            assert code == 0 and "Traceback" not in stderr, stderr[-3000:]


def observation(seed: int, spelling: str = "openpi") -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    images = [rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8) for _ in CAMERAS]
    state = rng.normal(size=8)
    prompt = f"lift the cube {seed}"
    if spelling == "openpi":  # what openpi's examples/libero/main.py sends
        return {
            "observation/image": images[0],
            "observation/wrist_image": images[1],
            "observation/state": state,
            "prompt": prompt,
        }
    return {
        "images": dict(zip(CAMERAS, images, strict=True)),
        "proprio": state,
        "instruction": prompt,
    }


def in_process(reference: VLAPolicy, observations: list[dict[str, Any]]) -> list[np.ndarray]:
    """The reference's chunks, openpi's keys mapped here by hand as docs/serving.md says."""
    ours = [
        {
            "images": {
                CAMERAS[0]: o["observation/image"],
                CAMERAS[1]: o["observation/wrist_image"],
            },
            "proprio": o["observation/state"],
            "instruction": o["prompt"],
        }
        if "prompt" in o
        else o
        for o in observations
    ]
    return reference.act_batch(ours)


def test_wire_format_is_openpis() -> None:
    """Our msgpack-numpy against openpi-client's own module, both ways."""
    value = {
        "image": np.arange(24, dtype=np.uint8).reshape(2, 4, 3),
        "state": np.linspace(-1, 1, 8),
        "half": np.ones((2, 3), np.float16),
        "scalar": np.float32(1.5),
        "nested": {"prompt": "pick", "list": [1, 2.5, None, True]},
    }
    for decoded in (unpackb(msgpack_numpy.packb(value)), msgpack_numpy.unpackb(packb(value))):
        assert decoded.keys() == value.keys() and decoded["nested"] == value["nested"]
        for key in ("image", "state", "half", "scalar"):
            assert decoded[key].dtype == value[key].dtype, key
            np.testing.assert_array_equal(decoded[key], value[key])
    with pytest.raises(WireError, match="dtype object"):
        packb({"x": np.array([None], dtype=object)})
    forged = msgpack_numpy.packb({"x": np.zeros(2)}).replace(b"<f8", b"|O8")
    with pytest.raises(WireError, match="not accepted"):
        unpackb(forged)
    with pytest.raises(WireError, match="not an openpi msgpack-numpy message"):
        unpackb(b"\xc1 not msgpack")


def test_schema_reads_both_spellings_and_names_what_is_wrong() -> None:
    schema = ObservationSchema(tuple(CAMERAS), 8)
    ours, openpi = schema.parse(observation(1, "ours")), schema.parse(observation(1, "openpi"))
    assert ours["instruction"] == openpi["instruction"] == "lift the cube 1"
    np.testing.assert_array_equal(ours["proprio"], openpi["proprio"])
    for camera in CAMERAS:
        np.testing.assert_array_equal(ours["images"][camera], openpi["images"][camera])
    both = {**observation(1), "proprio": np.zeros(8)}
    with pytest.raises(ObservationError, match="both 'proprio' and 'observation/state' given"):
        schema.parse(both)
    no_prompt = {k: v for k, v in observation(1).items() if k != "prompt"}
    with pytest.raises(ObservationError, match="missing 'instruction' or 'prompt'"):
        schema.parse(no_prompt)
    assert ObservationSchema(tuple(CAMERAS), 8, "stack").parse(no_prompt)["instruction"] == "stack"


def test_openpi_client_gets_the_in_process_actions(server: Server, reference: VLAPolicy) -> None:
    client = server.client()
    meta = client.get_server_metadata()
    assert meta["cameras"] == CAMERAS and meta["action_horizon"] == 8 and meta["action_dim"] == 7
    assert meta["openpi_keys"]["observation/wrist_image"] == "images/robot0_eye_in_hand"
    assert meta["camera_fovy"] is None  # trained at the scene's own (a LIBERO client checks it)
    requests = [observation(seed, spelling) for seed in range(4) for spelling in ("openpi", "ours")]
    expected = [in_process(reference, [o])[0] for o in requests]
    for request, actions in zip(requests, expected, strict=True):
        answer = client.infer(request)
        assert answer["actions"].shape == (8, 7) and answer["actions"].dtype == np.float32
        np.testing.assert_array_equal(answer["actions"], actions)
        assert answer["policy_timing"]["batch_size"] == 1
    assert not np.allclose(expected[0], expected[2])  # different observations, different actions
    broker = ActionChunkBroker(client, action_horizon=meta["action_horizon"])  # the robot loop's
    steps = [broker.infer(requests[step // 8 * 2])["actions"] for step in range(16)]
    np.testing.assert_array_equal(np.stack(steps), np.concatenate([expected[0], expected[2]]))
    health = f"http://{server.host}:{server.port}/healthz"
    with urllib.request.urlopen(health, timeout=10) as response:  # openpi's health check
        assert response.read() == b"OK\n"


def _without(key: str) -> dict[str, Any]:
    return {k: v for k, v in observation(0).items() if k != key}


MALFORMED: dict[str, tuple[dict[str, Any], str]] = {
    "missing image": (
        _without("observation/wrist_image"),
        "missing 'images/robot0_eye_in_hand' or 'observation/wrist_image'",
    ),
    "missing state": (_without("observation/state"), "missing 'proprio' or 'observation/state'"),
    "channels first": (
        {**observation(0), "observation/image": np.zeros((3, SIZE, SIZE), np.uint8)},
        r"'observation/image' has shape \(3, 64, 64\); send one RGB image \(H, W, 3\)",
    ),
    "grey image": (
        {**observation(0), "observation/wrist_image": np.zeros((SIZE, SIZE), np.uint8)},
        r"'observation/wrist_image' has shape \(64, 64\)",
    ),
    "float image": (
        {**observation(0), "observation/image": np.zeros((SIZE, SIZE, 3), np.float32)},
        "'observation/image' has dtype float32; send uint8",
    ),
    "cameras of two sizes": (
        {**observation(0), "observation/image": np.zeros((32, 32, 3), np.uint8)},
        "the cameras' images differ in size",
    ),
    "nan in the state": (
        {**observation(0), "observation/state": np.array([0, 0, np.nan, 0, 0, 0, 0, 0])},
        r"'observation/state' has non-finite values at \[2\]: \[nan\]",
    ),
    "inf in the state": (
        {**observation(0), "observation/state": np.full(8, np.inf)},
        r"'observation/state' has non-finite values at \[0, 1, 2",
    ),
    "short state": (
        {**observation(0), "observation/state": np.zeros(7)},
        r"'observation/state' has shape \(7,\); this policy takes \(8,\)",
    ),
    "prompt not a string": ({**observation(0), "prompt": 3}, "'prompt' is a string, got a int"),
    # Issue 62: what one request may cost is bounded (these held the forward for 16-89 s).
    "a 1100 x 1000 image": (
        {
            **observation(0),
            "observation/image": np.zeros((1100, 1000, 3), np.uint8),
            "observation/wrist_image": np.zeros((1100, 1000, 3), np.uint8),
        },
        r"'observation/image' has 1100 x 1000 = 1100000 pixels; this server takes at most 1048576",
    ),  # fmt: skip
    "a 4096 x 64 image": (
        {
            **observation(0),
            "observation/image": np.zeros((4096, 64, 3), np.uint8),
            "observation/wrist_image": np.zeros((4096, 64, 3), np.uint8),
        },
        r"'observation/image' is 4096 x 64, more than 4:1",
    ),  # fmt: skip
    "a 16 KB prompt": (
        {**observation(0), "prompt": "pick " * 3200},
        "'prompt' has 16000 characters; this server takes instructions of at most 256 tokens",
    ),
    "a prompt of 300 tokens": (
        {**observation(0), "prompt": "x" * 300},
        "'prompt' has 300 tokens; this server takes at most 256",
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_observation_gets_an_error_naming_it_and_the_server_goes_on(
    case: str, server: Server, reference: VLAPolicy
) -> None:
    request, message = MALFORMED[case]
    client = server.client()
    with pytest.raises(RuntimeError, match=message):
        client.infer(request)
    good = observation(5)
    expected = in_process(reference, [good])[0]
    np.testing.assert_array_equal(client.infer(good)["actions"], expected)  # same connection
    np.testing.assert_array_equal(server.client().infer(good)["actions"], expected)


def test_a_message_that_is_not_msgpack_gets_an_error(server: Server) -> None:
    with websockets.sync.client.connect(f"ws://{server.host}:{server.port}") as ws:
        ws.recv()  # the metadata
        ws.send(b"\xc1 not msgpack")
        assert "not an openpi msgpack-numpy message" in ws.recv()
        ws.send("a text frame")
        assert "binary msgpack" in ws.recv()


CLIENTS, REQUESTS = 16, 50
LOAD_TIMEOUT = 600  # seconds; about 40 on a busy 2-core machine


def test_16_clients_x_50_requests_each_get_their_own_answers(
    server: Server, reference: VLAPolicy
) -> None:
    """Every client sends its own observations and checks each answer against the in-process
    policy; meanwhile one client stalls in the handshake, one vanishes with a request in flight
    and one never reads its answers: nobody waits for them."""
    requests = [[observation(1000 * c + i) for i in range(REQUESTS)] for c in range(CLIENTS)]
    flat = [o for per_client in requests for o in per_client]
    answers = [a for i in range(0, len(flat), 16) for a in in_process(reference, flat[i : i + 16])]
    expected = [answers[c * REQUESTS : (c + 1) * REQUESTS] for c in range(CLIENTS)]

    url = f"ws://{server.host}:{server.port}"
    with socket.create_connection((server.host, server.port)) as stalled:
        stalled.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n")  # and never the rest
        with websockets.sync.client.connect(url, max_size=None) as vanished:
            vanished.recv()
            vanished.send(msgpack_numpy.packb(observation(7)))
        with websockets.sync.client.connect(url, max_size=None) as deaf:
            for seed in range(3):
                deaf.send(msgpack_numpy.packb(observation(seed)))
            sizes = _drive_clients((server.host, server.port), requests, expected)
    assert len(sizes) == CLIENTS * REQUESTS
    assert 1 < max(sizes) <= 16, "requests that arrived together were batched"


def _drive_clients(
    address: tuple[str, int], requests: list[list[dict]], expected: list[list[np.ndarray]]
) -> list[int]:
    """One thread and connection per client, all starting together; the batch size of every
    answer, each answer checked against ``expected``."""
    start = threading.Barrier(len(requests))

    def run(index: int) -> list[int]:
        client = WebsocketClientPolicy(*address)
        start.wait(timeout=120)
        sizes = []
        for request, actions in zip(requests[index], expected[index], strict=True):
            answer = client.infer(request)
            np.testing.assert_allclose(answer["actions"], actions, rtol=1e-5, atol=1e-5)
            sizes.append(answer["policy_timing"]["batch_size"])
        return sizes

    pool = ThreadPoolExecutor(len(requests))
    try:
        futures = [pool.submit(run, index) for index in range(len(requests))]
        _, late = wait(futures, timeout=LOAD_TIMEOUT)
        assert not late, f"{len(late)} clients still waiting after {LOAD_TIMEOUT} s"
        return [size for future in futures for size in future.result()]
    finally:  # a client stuck in recv ends when the fixture stops the server
        pool.shutdown(wait=False, cancel_futures=True)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_the_server_cleanly(
    signum: signal.Signals, export: Path, tmp_path: Path
) -> None:
    server = start_server(export, tmp_path)
    client = server.client()
    client.infer(observation(0))
    code, stderr = server.stop(signum)
    assert code == 0 and f"stopped ({signum.name})" in stderr and "Traceback" not in stderr
    with pytest.raises(websockets.ConnectionClosed) as closed:
        client.infer(observation(0))
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1001  # going away
    with socket.create_server((server.host, server.port)):  # the port is free again
        pass


def test_bf16_autocast_on_cpu_changes_the_actions_a_little(
    export: Path, reference: VLAPolicy
) -> None:
    request = ObservationSchema(tuple(CAMERAS), 8).parse(observation(3))
    full = reference.act_batch([request])[0]
    served = ServedPolicy(str(export), torch.device("cpu"), "32-true").act_batch([request])[0]
    mixed = ServedPolicy(str(export), torch.device("cpu"), "bf16-mixed").act_batch([request])[0]
    np.testing.assert_array_equal(served, full)
    assert not np.array_equal(mixed, full) and np.allclose(mixed, full, atol=0.1, rtol=0.1)


@pytest.mark.parametrize(
    "args,message",
    [
        (["--device", "cuda"], "--device cuda is not usable here"),
        (["--device", "tpu9"], "--device tpu9 is not usable here"),
        (["--precision", "16-mixed", "--device", "cpu"], "16-mixed needs a GPU"),
        (["--max-batch", "0"], "--max-batch must be >= 1"),
        (["--max-connections", "0"], "--max-connections must be >= 1"),
        (["--max-aspect", "0.5"], "--max-aspect must be >= 1, got 0.5"),
        (["--idle-timeout-s", "-1"], "--idle-timeout-s must be >= 0"),
        (["--port", "70000"], "--port 70000 is not a port"),
    ],
)
def test_bad_arguments_are_one_line(
    args: list[str], message: str, export: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["serve", "--ckpt", str(export), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err


def test_a_taken_port_is_refused_before_loading(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        # The checkpoint does not exist: the port is checked first, as loading can take minutes.
        assert main(["serve", "--ckpt", str(tmp_path / "none"), "--port", str(port)]) == 2
    assert f"port {port} on 127.0.0.1 is in use" in capsys.readouterr().err


@contextmanager
def server_in_thread(policy: ServedPolicy, **settings: Any) -> Iterator[tuple[str, int]]:
    """``PolicyServer`` on its own event loop in a thread of this process (no signals)."""
    schema = ObservationSchema.of(policy.spec, settings.pop("default_prompt", None))
    server = PolicyServer(policy.act_batch, schema, {}, **settings)
    loop = asyncio.new_event_loop()
    stop = asyncio.Event()
    sock = socket.create_server(("127.0.0.1", 0))
    thread = threading.Thread(target=loop.run_until_complete, args=(server.run(sock, stop),))
    thread.start()
    try:
        yield sock.getsockname()
    finally:
        loop.call_soon_threadsafe(stop.set)
        thread.join(timeout=60)
        loop.close()


def test_max_batch_window_and_default_prompt_have_their_effect(
    export: Path, reference: VLAPolicy
) -> None:
    policy = ServedPolicy(str(export), torch.device("cpu"), "32-true")
    requests = [[observation(10 * c + i) for i in range(5)] for c in range(4)]
    for request in (r for per_client in requests for r in per_client):
        del request["prompt"]
    expected = [in_process(reference, [{**r, "prompt": "stack"} for r in rs]) for rs in requests]
    with server_in_thread(policy, max_batch=1, default_prompt="stack") as address:
        assert set(_drive_clients(address, requests, expected)) == {1}
    with server_in_thread(policy, batch_window=0.5) as address:
        client = WebsocketClientPolicy(*address)
        start = time.monotonic()
        client.infer(observation(0))  # alone: it waits out the window for company
        assert time.monotonic() - start >= 0.5


# Issue 62: no NaN reaches a robot; one client cannot starve or break the others.

BANG = 4  # the tiny byte-level tokenizer's id of "!"


def _export_with(folder: Path, corrupt: Any) -> Path:
    rng = np.random.default_rng(0)
    stats = compute_statistics(rng.normal(size=(200, 7)), rng.normal(size=(200, 8)), 4)
    spec = DataSpec(cameras=CAMERAS, image_size=SIZE, statistics={"capvector": stats})
    torch.manual_seed(0)
    module = VLAModule(backbone="openvla-oft-tiny", data_spec=spec)
    # Corrupted after a clean export, as a bad disk or a hand-edited file leaves it: the
    # module's own export refuses non-finite weights.
    folder = module.export(folder)
    with torch.no_grad():
        corrupt(module.backbone)
    poisoned = {n: p for n, p in module.backbone.named_parameters() if not p.isfinite().all()}
    for weights in folder.glob("*.safetensors"):
        tensors = load_file(weights)
        for key in list(tensors):
            # The file may prefix the backbone's names; "projector.fc1.bias" is not a suffix of
            # "proprio_projector.fc1.bias" at a dot.
            name = next((n for n in poisoned if key == n or key.endswith(f".{n}")), None)
            if name is not None:
                tensors[key] = poisoned[name].detach().clone().to(tensors[key].dtype)
        save_file(tensors, weights, metadata={"format": "pt"})
    return folder


@pytest.fixture(scope="module")
def bang_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An export whose embedding of "!" is NaN: prompts with "!" give NaN actions, others do
    not (a corrupted row, as a bad fine-tune or a flipped bit leaves one)."""

    def corrupt(backbone: Any) -> None:
        backbone.language_model.model.embed_tokens.weight[BANG] = float("nan")

    return _export_with(tmp_path_factory.mktemp("bang") / "export", corrupt)


def test_a_non_finite_answer_is_never_sent_and_the_server_goes_on(
    bang_export: Path, tmp_path: Path
) -> None:
    reference = load_module(bang_export).eval()
    policy = VLAPolicy(reference.backbone, reference.data_spec)
    bad = {**observation(1), "prompt": "lift the cube!"}
    assert not np.isfinite(in_process(policy, [bad])[0]).any()  # the defect, in process
    good = observation(2)
    expected = in_process(policy, [good])[0]
    assert np.isfinite(expected).all()
    server = start_server(bang_export, tmp_path, "--batch-window-ms", "500")
    try:
        client = server.client()
        with pytest.raises(RuntimeError, match="hold 56 non-finite values of 56 .*not sent"):
            client.infer(bad)
        np.testing.assert_array_equal(client.infer(good)["actions"], expected)  # goes on
        # Batched with the bad one (the window is 0.5 s), the bystander gets its actions.
        bystander = server.client()
        with ThreadPoolExecutor(2) as pool:
            refused = pool.submit(client.infer, bad)
            answered = pool.submit(bystander.infer, good)
            answer = answered.result(timeout=120)
            with pytest.raises(RuntimeError, match="non-finite"):
                refused.result(timeout=120)
        np.testing.assert_allclose(answer["actions"], expected, rtol=1e-5, atol=1e-5)  # padded
        assert answer["policy_timing"]["batch_size"] == 2
    finally:
        code, stderr = server.stop()
    assert code == 0 and "non-finite values; not sent" in stderr and "Traceback" not in stderr


def test_an_export_that_answers_nan_is_refused_at_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def corrupt(backbone: Any) -> None:
        for parameter in backbone.parameters():
            parameter.fill_(float("nan"))

    export = _export_with(tmp_path / "export", corrupt)
    assert main(["serve", "--ckpt", str(export), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "answers a blank observation with non-finite actions (56 of 56)" in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_a_failed_batch_is_answered_one_at_a_time(
    export: Path, reference: VLAPolicy, tmp_path: Path
) -> None:
    """The issue's 64 KB prompt, let through by a raised bound, fails its forward allocating
    tens of GB (here at once: the server may map 4 GB); the bystander batched with it gets its
    own actions, the abuser one line, and the server goes on."""
    server = start_server(
        export, tmp_path, "--batch-window-ms", "1000", "--max-prompt-tokens", "1000000",
        address_space=4 * 2**30,
    )  # fmt: skip
    try:
        abuser, bystander = server.client(), server.client()
        huge = {**observation(1), "prompt": "x" * 65536}
        good = observation(2)
        with ThreadPoolExecutor(2) as pool:
            refused = pool.submit(abuser.infer, huge)
            answered = pool.submit(bystander.infer, good)
            answer = answered.result(timeout=300)
            with pytest.raises(RuntimeError, match="the policy failed on this request: "):
                refused.result(timeout=300)
        np.testing.assert_array_equal(answer["actions"], in_process(reference, [good])[0])
        assert answer["policy_timing"]["batch_size"] == 1  # answered alone, after the batch
        np.testing.assert_array_equal(abuser.infer(good)["actions"], answer["actions"])
    finally:
        code, stderr = server.stop()
    assert code == 0 and "failed on a batch of 2" in stderr and "answering each alone" in stderr


def test_idle_connections_are_closed_and_the_connection_cap_holds(export: Path) -> None:
    policy = ServedPolicy(str(export), torch.device("cpu"), "32-true")
    with server_in_thread(policy, idle_timeout=1.0, max_connections=2) as address:
        first, second = WebsocketClientPolicy(*address), WebsocketClientPolicy(*address)
        with pytest.raises(websockets.ConnectionClosed) as refused:
            WebsocketClientPolicy(*address)
        assert (
            refused.value.rcvd.code == 1013 and "cap of 2 connections" in refused.value.rcvd.reason
        )
        first.infer(observation(0))  # a request resets the idle clock
        time.sleep(2.0)
        for idle in (first, second):
            with pytest.raises(websockets.ConnectionClosed) as closed:
                idle.infer(observation(0))
            assert closed.value.rcvd.code == 1000 and "idle for 1 s" in closed.value.rcvd.reason
        WebsocketClientPolicy(*address).infer(observation(0))  # the closed ones freed their slots


def test_a_message_beyond_the_bounds_closes_its_connection_unread(
    server: Server, reference: VLAPolicy
) -> None:
    """The issue's 48 MB request (two 8,000,000 x 1 images) and 50 MB prompt: larger than any
    request the bounds let through, they close their connection (1009) before being read."""
    thin = np.zeros((8_000_000, 1, 3), np.uint8)
    for request in (
        {**observation(0), "observation/image": thin, "observation/wrist_image": thin},
        {**observation(0), "prompt": "x" * 50_000_000},
    ):
        client = server.client()
        with pytest.raises(websockets.ConnectionClosed) as closed:
            client.infer(request)
        assert closed.value.rcvd.code == 1009  # message too big
    good = observation(5)
    np.testing.assert_array_equal(
        server.client().infer(good)["actions"], in_process(reference, [good])[0]
    )


WELL_BEHAVED, ROUNDS = 15, 12
ABUSER = """
import sys, time, numpy as np, websockets, websockets.sync.client as ws
from openpi_client import msgpack_numpy
url = f"ws://{sys.argv[1]}:{sys.argv[2]}"
base = {"observation/image": np.zeros((64, 64, 3), np.uint8),
        "observation/wrist_image": np.zeros((64, 64, 3), np.uint8),
        "observation/state": np.zeros(8), "prompt": "lift"}
thin, wide = np.zeros((8_000_000, 1, 3), np.uint8), np.zeros((1100, 1000, 3), np.uint8)
abuse = [msgpack_numpy.packb(request) for request in (  # packed once: its CPU goes on sending
    {**base, "observation/image": thin, "observation/wrist_image": thin},
    {**base, "observation/image": wide, "observation/wrist_image": wide},
    {**base, "prompt": "pick " * 3200},
    {**base, "prompt": "x" * 65536},
    {**base, "prompt": "x" * 50_000_000},
)]
def connect():
    connection = ws.connect(url, compression=None, max_size=None)
    connection.recv()  # the metadata
    return connection
idle, client = [], connect()
while True:
    for message in abuse:
        time.sleep(0.1)  # abusive in content; a flood of 100s of MB/s is the network's to stop
        try:
            client.send(message)
            print("refused" if isinstance(client.recv(), str) else "answered", flush=True)
        except websockets.ConnectionClosed:
            print("closed", flush=True)
            client = connect()
    if len(idle) < 8:
        idle.append(connect())
"""


def test_one_abusive_client_does_not_slow_15_others_by_more_than_2x(
    server: Server, tmp_path: Path
) -> None:
    """15 clients' request latency alone (the baseline phase), then with one client sending the
    issue's abuse in a loop from its own process: two 8,000,000 x 1 images (48 MB), two 1100 x
    1000 ones, 16 KB, 64 KB and 50 MB prompts, and connections it opens and leaves idle. It
    waits 0.1 s between requests: what it sends is the abuse; a flood of hundreds of MB/s over
    loopback would take the 2 cores from the server whatever the server did. Medians of the same clients in the same test, so a
    loaded machine moves both phases alike."""
    address = (server.host, server.port)
    good = [[observation(5000 + 100 * c + i) for i in range(ROUNDS)] for c in range(WELL_BEHAVED)]

    def phase(abuse: bool, folder: Path) -> tuple[list[float], list[str]]:
        # The abuser is its own process, so its packing of 50 MB does not hold this one's GIL.
        out = folder / f"abuser_{abuse}.txt"
        out.write_text("")
        noisy = None
        if abuse:
            with out.open("w") as stdout:
                noisy = subprocess.Popen(
                    [sys.executable, "-c", ABUSER, *map(str, address)], stdout=stdout,
                    stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": "1"},
                )  # fmt: skip
            deadline = time.monotonic() + 120
            while out.read_text().count("\n") < 5 and noisy.poll() is None:  # under way
                assert time.monotonic() < deadline, out.read_text()[-2000:]
                time.sleep(0.05)

        start = threading.Barrier(WELL_BEHAVED)

        def well_behaved(index: int) -> list[float]:
            client = WebsocketClientPolicy(*address)
            start.wait(timeout=120)
            latencies = []
            for request in good[index]:
                begin = time.monotonic()
                client.infer(request)
                latencies.append(time.monotonic() - begin)
            return latencies

        pool = ThreadPoolExecutor(WELL_BEHAVED)
        try:
            futures = [pool.submit(well_behaved, c) for c in range(WELL_BEHAVED)]
            _, late = wait(futures, timeout=LOAD_TIMEOUT)
            assert not late, f"{len(late)} clients still waiting after {LOAD_TIMEOUT} s"
        finally:
            pool.shutdown(wait=False, cancel_futures=True)
            if noisy is not None:
                assert noisy.poll() is None, out.read_text()[-2000:]  # it abused throughout
                noisy.kill()
                noisy.wait(timeout=60)
        return [t for future in futures for t in future.result()], out.read_text().split()

    baseline, _ = phase(False, tmp_path)
    abused, events = phase(True, tmp_path)
    refusals = len(events)
    ratio = float(np.median(abused) / np.median(baseline))
    print(f"median latency {np.median(baseline) * 1000:.0f} ms alone, "
          f"{np.median(abused) * 1000:.0f} ms beside the abuser ({refusals} refusals): x{ratio:.2f}")  # fmt: skip
    assert refusals >= 10 and "answered" not in events
    assert ratio <= 2.0, f"the abuser slowed the others' median latency {ratio:.2f}x"
