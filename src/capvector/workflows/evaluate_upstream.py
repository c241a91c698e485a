"""``capvector evaluate --backend upstream``: LIBERO's protocol on upstream LIBERO (robosuite 1.4,
MuJoCo 2.3.7) instead of this project's port, as openpi evaluates its LIBERO policies.

robosuite 1.4 cannot share an environment with our robosuite 1.5, so the simulator runs in its own
(``tools/libero/install_libero14.sh`` makes it): this process loads the policy as ``capvector
serve`` does and serves it on a free local port from a thread, and ``tools/libero/eval_client.py``
run by that environment's python steps LIBERO and asks it for chunks. The client keeps the port's
trial protocol (trial i from official initial state i, fixtures drawn from seed 1,000,000 + i, the
suite's step limit, the whole chunk executed, the gripper binarised: its docstring), so the two
backends differ by the simulator and its renderer only, and its rows are ``evaluate --json``'s.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import socket
import subprocess
import tempfile
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capvector.errors import CapVectorError
from capvector.eval.device import Precision, resolve_device, resolve_precision

if TYPE_CHECKING:
    from capvector.eval.rollout import ProgressLines

UPSTREAM_ENV_VAR = "CAPVECTOR_LIBERO14"
"""Where the upstream environment is when ``--upstream-env`` is not given."""
DEFAULT_UPSTREAM_ENV = Path("~/.cache/capvector/libero14")
"""Where ``tools/libero/install_libero14.sh`` puts it by default."""
TOOLS = Path(__file__).resolve().parents[3] / "tools" / "libero"
INSTALL_SCRIPT = TOOLS / "install_libero14.sh"
CLIENT = TOOLS / "eval_client.py"
CLIENT_ERROR = "eval_client.py: error: "
"""How the client's refusals start (``ERROR`` there)."""
CLIENT_EPISODE = re.compile(r"\w+/\d+/\d+: (success|failure) after \d+ steps")
"""The client's line for an episode that ended: ``libero_spatial/5/3: failure after 220 steps``."""


def upstream_python(env: str | os.PathLike[str] | None = None) -> Path:
    """The python of the upstream LIBERO environment: ``env``, else ``$CAPVECTOR_LIBERO14``, else
    the install script's default folder. A missing one is refused with the command that makes
    it."""
    given = env or os.environ.get(UPSTREAM_ENV_VAR) or DEFAULT_UPSTREAM_ENV
    folder = Path(given).expanduser()
    python = folder / "bin" / "python"
    if not python.is_file():
        where = "--upstream-env" if env else UPSTREAM_ENV_VAR if os.environ.get(
            UPSTREAM_ENV_VAR) else "the default folder"  # fmt: skip
        raise CapVectorError(
            f"no upstream LIBERO environment at {folder} ({where}): install it with "
            f"`{_shown(INSTALL_SCRIPT)} {folder}` (robosuite 1.4, MuJoCo 2.3.7; ~1 GB)"
        )
    if not CLIENT.is_file():
        raise CapVectorError(
            f"{CLIENT} is missing: --backend upstream runs LIBERO's client from a source "
            "checkout of capvector (pip install -e .)"
        )
    return python


def _shown(path: Path) -> str:
    """``path`` relative to the working folder when it is under it (as a user would type it)."""
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def evaluate_upstream(
    ckpt: str,
    suite: str,
    tasks: Sequence[int] | None,
    trials: int,
    *,
    max_steps: int | None = None,
    image_size: int | None = None,
    execute_steps: int | None = None,
    upstream_env: str | None = None,
    device: str | None = None,
    precision: Precision | None = None,
    lines: ProgressLines | None = None,
) -> list[dict[str, Any]]:
    """The rows of ``evaluate --json`` (one per task, every trial in ``per_episode``), each with
    its ``stack`` and ``renderer``, from LIBERO on robosuite 1.4 driving ``ckpt``'s policy;
    ``lines`` counts the client's episodes as they end."""
    from capvector.workflows.serve import ServedPolicy  # torch; after the cheap refusals

    python = upstream_python(upstream_env)
    torch_device = resolve_device(device)
    precision = resolve_precision(torch_device, precision)
    policy = ServedPolicy(ckpt, torch_device, precision)
    policy.warm_up()
    with served(policy) as port, tempfile.TemporaryDirectory(prefix="capvector-upstream-") as tmp:
        out = Path(tmp) / "rows.json"
        command = [
            str(python), str(CLIENT), "--port", str(port), "--suite", suite,
            "--trials", str(trials), "--json", str(out), "--connect-timeout", "60",
        ]  # fmt: skip
        if tasks is not None:
            command += ["--tasks", *map(str, tasks)]
        for flag, value in (("--max-steps", max_steps), ("--image-size", image_size),
                            ("--replan-steps", execute_steps)):  # fmt: skip
            if value is not None:
                command += [flag, str(value)]
        env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
        _run_client(command, env, lines)
        return json.loads(out.read_text())


def _run_client(command: list[str], env: dict[str, str], lines: ProgressLines | None) -> None:
    """Run the client, its lines through to stdout (robosuite 1.4's warnings left out), each of
    its episodes counted in ``lines``; a client that fails is one line: its refusal, else its last
    words."""
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
        stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert process.stdout is not None
    tail: list[str] = []
    refusals: list[str] = []  # what the client said is wrong, one line each
    for line in process.stdout:
        if "robosuite WARNING" in line:
            continue
        tail = [*tail[-4:], line.rstrip()]
        if CLIENT_ERROR in line:
            refusals.append(line.split(CLIENT_ERROR, 1)[1].rstrip())
        print(line, end="", flush=True)
        if lines is not None and (episode := CLIENT_EPISODE.match(line)):
            lines.update(episode[1] == "success")
    if process.wait() != 0:
        if refusals:
            raise CapVectorError(f"LIBERO's client on robosuite 1.4 refused: {refusals[-1]}")
        last = next((t for t in reversed(tail) if t.strip()), "no output")
        raise CapVectorError(
            f"LIBERO's client in the upstream environment failed (exit {process.returncode}): "
            f"{last}; run `{' '.join(command[:2])} --help` there to check the environment"
        )


@contextmanager
def served(policy: Any, host: str = "127.0.0.1") -> Iterator[int]:
    """Serve ``policy`` (a :class:`~capvector.workflows.serve.ServedPolicy`) on a free port of
    ``host`` from a thread of this process; yields the port, stops and joins on exit. One
    connection at a time is what the client needs, so no batching window; no keepalive pings
    either: the client answers them only between its steps, and a loaded machine (12 processes
    on 2 cores) kept it from answering within websockets' 20 s, which closed the connection in
    the middle of a trial."""
    from capvector.serve.schema import ObservationSchema
    from capvector.serve.server import PolicyServer

    schema = ObservationSchema.of(policy.spec, count_tokens=policy.count_tokens)
    server = PolicyServer(
        policy.act_batch, schema, policy.metadata(schema, 1), max_batch=1, batch_window=0.0,
        idle_timeout=None, max_connections=2, keepalive=None,
    )  # fmt: skip
    loop = asyncio.new_event_loop()
    stop = asyncio.Event()
    failure: list[BaseException] = []

    def run() -> None:
        try:
            loop.run_until_complete(server.run(sock, stop))
        except BaseException as err:  # the client then fails to connect; say why afterwards
            failure.append(err)
        finally:
            loop.close()

    with socket.create_server((host, 0)) as sock:
        thread = threading.Thread(target=run, name="capvector-upstream-serve", daemon=True)
        thread.start()
        try:
            yield sock.getsockname()[1]
        finally:
            if thread.is_alive():
                loop.call_soon_threadsafe(stop.set)
            thread.join(timeout=60)
    if failure:
        raise CapVectorError(f"the policy server stopped: {failure[0]!r}") from failure[0]
