"""``capvector``: LightningCLI for training (fit/validate) plus the recipe's tools.

Training subcommands go to LightningCLI (YAML configs, omegaconf interpolation). Tool subcommands
are looked up in ``TOOLS`` and imported only when called, so ``capvector extract`` does not pay for
importing the simulator and ``capvector fit`` does not pay for the vector tools.
"""

from __future__ import annotations

import errno
import importlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

from capvector.errors import CapVectorError
from capvector.io.outputs import disk_full, no_room
from capvector.workflows.fit import run_lightning_cli

# VLAModule has no test_step or predict_step (evaluation is the validation loop; `capvector
# evaluate` and `serve` run a policy), so LightningCLI's test and predict are not offered.
LIGHTNING_SUBCOMMANDS = ("fit", "validate")

TOOLS: dict[str, tuple[str, str]] = {  # name: ("module:function", help), imported when called
    "backbone-info": (
        "capvector.workflows.backbone_info:backbone_info_main",
        "parameter counts of a preset",
    ),
    "export": (
        "capvector.workflows.export:export_main",
        "export a checkpoint to a safetensors folder",
    ),
    "import-original": (
        "capvector.workflows.export:import_original_main",
        "original checkpoint -> export",
    ),
    "demos": (
        "capvector.workflows.demos:main",
        "record scripted robosuite or LIBERO demonstrations",
    ),
    "evaluate": ("capvector.workflows.evaluate:main", "MuJoCo rollouts of a checkpoint"),
    "recipe": ("capvector.cli:recipe_main", "run the whole recipe as resumable stages"),
    "sweep-scale": ("capvector.workflows.sweep:main", "choose the merge scale λ"),
    "extract": ("capvector.workflows.vectors:extract_main", "capability vector = aux - sft"),
    "merge": ("capvector.workflows.vectors:merge_main", "base + sum of scaled vectors"),
    "compose": ("capvector.workflows.vectors:compose_main", "combine vectors (sum, TIES)"),
    "inspect": ("capvector.workflows.inspection:main", "norms, cosines and plots of vectors"),
    "report": ("capvector.workflows.report:main", "success vs steps of a recipe's arms"),
    "serve": (
        "capvector.workflows.serve:main",
        "answer observations over openpi's websocket protocol",
    ),
    "push": ("capvector.workflows.push:main", "upload an export or vector to the Hugging Face Hub"),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Its bad input (a ``CapVectorError`` raised anywhere, or an environment
    failure such as a full disk) is printed here as one line, for every command alike; anything
    else is a bug and keeps its traceback."""
    try:
        return _run(list(sys.argv[1:] if argv is None else argv), from_shell=argv is None)
    except BrokenPipeError:
        # The reader left (`capvector --help | head -1`): what is left to print goes nowhere, as
        # Python's docs advise (signal.html, "Note on SIGPIPE"), instead of a traceback at exit.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE


def _run(args: list[str], from_shell: bool) -> int:
    if not args or args[0] in ("-h", "--help"):
        print(_usage())
        return 0
    command, rest = args[0], args[1:]
    if command not in LIGHTNING_SUBCOMMANDS and command not in TOOLS:
        print(f"capvector: unknown command {command!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    try:
        if command in LIGHTNING_SUBCOMMANDS:
            # From a shell, LightningCLI reads sys.argv itself (it warns when given both).
            run_lightning_cli(None if from_shell else [command, *rest])
            return 0
        module, function = TOOLS[command][0].split(":")
        tool: Callable[[list[str]], int] = getattr(importlib.import_module(module), function)
        with _terminate_as_exit():
            return int(tool(rest) or 0)
    except (KeyboardInterrupt, Exception) as exc:
        return _failed(f"capvector {command}", exc)


def run_module_tool(name: str, tool: Callable[[], int | None]) -> int:
    """A tool run as ``python -m capvector.workflows.NAME`` (outside the command table) with the
    commands' error path: its bad input is one line after ``name``, not a traceback."""
    try:
        with _terminate_as_exit():
            return int(tool() or 0)
    except (KeyboardInterrupt, Exception) as exc:
        return _failed(name, exc)


def _failed(name: str, exc: BaseException) -> int:
    """The exit code of a command that raised ``exc``, said in one line; a bug is raised again."""
    if isinstance(exc, KeyboardInterrupt):  # outputs are written atomically: none is half there
        print(f"{name}: interrupted", file=sys.stderr)
        return 130
    error, code = _reported(exc)
    if error is None:
        raise exc
    print(f"{name}: error: {error}", file=sys.stderr)
    return code


def recipe_main(argv: list[str]) -> int:
    """``capvector recipe``, told the commands its stages may run, so that a misspelt one is
    found before any stage runs (the recipe sits below this table and cannot import it)."""
    from capvector.workflows.recipe import main as recipe

    return recipe(argv, commands=[*LIGHTNING_SUBCOMMANDS, *TOOLS])


ENVIRONMENT_ERRORS = frozenset({errno.EROFS, errno.EACCES, errno.EPERM})
"""OSErrors that are the machine refusing (read-only, permissions), not a bug. A full disk is the
output's place to change, as bad input is: exit 2, naming the path."""


def _reported(exc: BaseException) -> tuple[BaseException | None, int]:
    """The error to print as one line and the exit code: bad input (exit 2), ours or ours wrapped
    (jsonargparse re-raises an error of a link's compute_fn, e.g. the data module's spec, as a
    ValueError caused by it), a full disk met by a writer other than ``io.outputs``' (Lightning's
    checkpoints, a logger), or the environment refusing (exit 1); ``None`` for a bug."""
    cause: BaseException | None = exc
    while cause is not None:
        if isinstance(cause, CapVectorError | FileExistsError):
            return cause, 2
        cause = cause.__cause__
    if disk_full(exc):
        return no_room(_written_path(exc) or "its output", "output", exc), 2
    if isinstance(exc, OSError) and exc.errno in ENVIRONMENT_ERRORS:
        return exc, 1
    return None, 0


def _written_path(exc: BaseException) -> str | None:
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.filename:
            return str(seen.filename)
        seen = seen.__cause__ or seen.__context__
    return None


@contextmanager
def _terminate_as_exit() -> Iterator[None]:
    """SIGTERM (``kill``, a scheduler's time limit) ends a tool as Ctrl-C does, by an exception, so
    the outputs' cleanup runs and removes their temporary folders; by default it ended the process
    on the spot and left them behind. (LightningCLI has its own SIGTERM handling.)"""

    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = signal.getsignal(signal.SIGTERM)
    # Only the main thread may set handlers; called from another thread, leave signals alone.
    install = threading.current_thread() is threading.main_thread() and previous is not None
    if install:
        signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        if install:
            signal.signal(signal.SIGTERM, previous)


def _usage() -> str:
    lines = ["usage: capvector COMMAND [...]", "", "training (LightningCLI, --config FILE.yaml):"]
    lines += [f"  {c}" for c in LIGHTNING_SUBCOMMANDS]
    lines += ["", "tools:"]
    lines += [f"  {name:<16} {help_}" for name, (_, help_) in TOOLS.items()]
    lines += ["", "Run `capvector COMMAND --help` for a command's options."]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
