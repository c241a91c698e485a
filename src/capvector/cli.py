"""``capvector``: LightningCLI for training (fit/validate) plus the recipe's tools.

Training subcommands go to LightningCLI (YAML configs, omegaconf interpolation). Tool subcommands
are looked up in ``TOOLS`` and imported only when called, so ``capvector extract`` does not pay for
importing the simulator and ``capvector fit`` does not pay for the vector tools.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import shlex
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capvector.errors import CapVectorError
from capvector.eval.device import Precision, precision_context, resolve_device, resolve_precision
from capvector.io.outputs import check_output
from capvector.profiling.settings import TrainingSettings
from capvector.tool_cli import Tool, run_tool
from capvector.workflows.fit import run_lightning_cli

if TYPE_CHECKING:
    import torch
    from jsonargparse import ArgumentParser

    from capvector.backbones import VLABackbone

# VLAModule has no test_step or predict_step (evaluation is the validation loop; `capvector
# evaluate` and `serve` run a policy), so LightningCLI's test and predict are not offered.
LIGHTNING_SUBCOMMANDS = ("fit", "validate")

TOOLS: dict[str, tuple[str, str]] = {  # name: ("module:function", help), imported when called
    "backbone-info": ("capvector.cli:backbone_info_main", "parameter counts of a preset"),
    "export": ("capvector.cli:export_main", "export a checkpoint to a safetensors folder"),
    "import-original": ("capvector.cli:import_original_main", "original checkpoint -> export"),
    "demos": ("capvector.sim.demos:main", "record scripted robosuite or LIBERO demonstrations"),
    "evaluate": ("capvector.workflows.evaluate:main", "MuJoCo rollouts of a checkpoint"),
    "recipe": ("capvector.workflows.recipe:main", "run the whole recipe as resumable stages"),
    "sweep-scale": ("capvector.workflows.sweep:main", "choose the merge scale λ"),
    "extract": ("capvector.vectors.cli:extract_main", "capability vector = aux - sft"),
    "merge": ("capvector.vectors.cli:merge_main", "base + sum of scaled vectors"),
    "compose": ("capvector.vectors.cli:compose_main", "combine vectors (sum, TIES)"),
    "inspect": ("capvector.workflows.inspection:main", "norms, cosines and plots of vectors"),
    "report": ("capvector.workflows.report:main", "success vs steps of a recipe's arms"),
    "serve": ("capvector.serve.cli:main", "answer observations over openpi's websocket protocol"),
    "push": ("capvector.workflows.push:main", "upload an export or vector to the Hugging Face Hub"),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Its bad input (a ``CapVectorError`` raised anywhere, or an environment
    failure such as a full disk) is printed here as one line, for every command alike; anything
    else is a bug and keeps its traceback."""
    args = list(sys.argv[1:] if argv is None else argv)
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
            run_lightning_cli(None if argv is None else [command, *rest])
            return 0
        module, function = TOOLS[command][0].split(":")
        tool: Callable[[list[str]], int] = getattr(importlib.import_module(module), function)
        with _terminate_as_exit():
            return int(tool(rest) or 0)
    except KeyboardInterrupt:  # outputs are written atomically: an interrupted one is not there
        print(f"capvector {command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        error, code = _reported(exc)
        if error is None:
            raise
        print(f"capvector {command}: error: {error}", file=sys.stderr)
        return code


ENVIRONMENT_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM})
"""OSErrors that are the machine refusing (full disk, quota, read-only, permissions), not a bug."""


def _reported(exc: BaseException) -> tuple[BaseException | None, int]:
    """The error to print as one line and the exit code: bad input (exit 2), ours or ours wrapped
    (jsonargparse re-raises an error of a link's compute_fn, e.g. the data module's spec, as a
    ValueError caused by it), or the environment refusing (exit 1); ``None`` for a bug."""
    cause: BaseException | None = exc
    while cause is not None:
        if isinstance(cause, CapVectorError | FileExistsError):
            return cause, 2
        cause = cause.__cause__
    if isinstance(exc, OSError) and exc.errno in ENVIRONMENT_ERRORS:
        return exc, 1
    return None, 0


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


def backbone_info_main(argv: list[str]) -> int:
    return run_tool(backbone_info_cli, argv, "backbone-info")


def backbone_info_cli(
    preset: str | None = None,
    /,
    *,
    list: bool = False,
    memory: bool = False,
    flops: bool = False,
    settings: TrainingSettings,
    steps: int = 100_000,
    mfu: float = 0.4,
    gpu_tflops: float = 989.0,
) -> None:
    """Parameter counts per component from a meta-device build (no memory, no download); with
    --memory the per-device training memory, with --flops the training FLOPs and GPU-hours.

    Args:
        preset: a registered preset; omit with --list
        list: list the registered presets
        memory: estimate per-device training memory
        flops: training FLOPs per sample, GPU-hours
        settings: the training run (each field an option: --batch, --precision, ...)
        steps: optimizer steps (--flops)
        mfu: model FLOPs utilisation (--flops)
        gpu_tflops: peak dense TFLOP/s (H100 bf16: 989)
    """
    import torch

    from capvector.backbones import build_backbone, list_presets

    if list or not preset:
        print("\n".join(list_presets()))
        return
    if memory:  # first: it checks the settings, so a typo fails before anything is printed
        from capvector.profiling.memory import describe, estimate_memory

        estimate = describe(estimate_memory(preset, settings), settings)
    with torch.device("meta"):
        model = build_backbone(preset)
    print(f"{preset} ({type(model).__name__})")
    rows = [
        (name, sum(p.numel() for p in child.parameters())) for name, child in model.named_children()
    ]
    capability = set(model.capability_parameter_names())
    in_vector = sum(p.numel() for n, p in model.named_parameters() if n in capability)
    total = sum(count for _, count in rows)
    width = max(len(name) for name, _ in rows)
    for name, count in rows:
        print(f"  {name:<{width}}  {count:>15,}")
    print(f"  {'total':<{width}}  {total:>15,}")
    print(f"  {'capability':<{width}}  {in_vector:>15,}  (parameters a capability vector covers)")
    if memory:
        print(estimate)
    if flops:
        from capvector.profiling.flops import estimate_flops

        batch, devices = settings.batch, settings.devices
        counted = estimate_flops(preset, batch_size=batch, lora_rank=settings.lora_rank)
        print(
            counted.table(
                steps=steps, batch_size=batch, devices=devices, mfu=mfu, gpu_tflops=gpu_tflops
            )
        )


def export_main(argv: list[str]) -> int:
    return run_tool(export_cli, argv, "export")


def export_cli(ckpt: str, out: str, overwrite: bool = False) -> None:
    """Export a Lightning checkpoint to a folder that `extract`, `merge` and `evaluate` read.

    Args:
        ckpt: Lightning checkpoint (.ckpt)
        out: output folder (written atomically)
        overwrite: replace an existing --out
    """
    from capvector.module import load_module

    check_output(out, overwrite, [ckpt])  # before loading the checkpoint
    folder = load_module(ckpt).export(out, overwrite=overwrite)
    print(f"exported {ckpt} to {folder}")


def import_original_main(argv: list[str]) -> int:
    """``capvector import-original``: ``import_original_cli``'s options and the family's own
    (``VLABackbone.import_options``), of the family of the preset ``argv`` names, or of every
    registered family when it names none (for ``--help``)."""
    from capvector.backbones import backbone_class, preset_config
    from capvector.backbones.base import registered_families

    peek = argparse.ArgumentParser(add_help=False)
    peek.add_argument("--preset")
    preset = peek.parse_known_args(argv)[0].preset
    families = registered_families()
    if preset is not None:
        families = {(family := preset_config(preset).family): backbone_class(family)}
    command = shlex.join(["capvector", "import-original", *argv])
    tool = Tool(import_original_cli, "import-original", skip=["command"])
    _add_import_options(tool.parser, families)
    tool.call(tool.parse(argv), command=command)
    return 0


def import_original_cli(
    preset: str,
    folder: str,
    out: str,
    override: str = "{}",
    overwrite: bool = False,
    device: str | None = None,
    precision: Precision | None = None,
    check: bool = True,
    *,
    command: str,
    **options: Any,
) -> None:
    """Convert an original project's checkpoint (OpenVLA-OFT run folder, LeRobot pi05 policy folder,
    StarVLA checkpoint + Qwen folder) into an export folder usable as ``--model.pretrained`` (θ_pre).
    The architecture comes from the checkpoint's own config files; statistics are always written.
    Each family adds its own options (below, by family; ``--preset P --help`` shows P's).

    Args:
        preset: the architecture, e.g. openvla-oft-7b, pi05-3b
        folder: original checkpoint folder (or StarVLA checkpoint file)
        out: export folder to write (atomically)
        override: JSON of config fields to change, e.g. '{"featurizer": {"depth": 2}}' (a nested
            object changes only the fields it names)
        overwrite: replace an existing --out
        device: where the imported model runs its check forward, e.g. cpu, cuda, cuda:1
            (default: cuda when there is one)
        precision: the check forward's precision: 32-true, bf16-mixed or 16-mixed (default:
            bf16-mixed on a GPU, 32-true elsewhere); the weights are written as imported
        check: run one forward on a blank observation before writing (--no-check: skip it)
        command: the command line, for the model card
        options: the family's ``import_options``
    """
    import json

    from capvector.backbones import backbone_class, preset_config

    try:
        overrides = json.loads(override)
    except json.JSONDecodeError as exc:
        raise CapVectorError(f"--override is not JSON ({exc}): {override!r}") from exc
    if not isinstance(overrides, dict):
        raise CapVectorError(f"--override must be a JSON object, got {override!r}")
    torch_device = resolve_device(device)
    precision = resolve_precision(torch_device, precision)  # refused before the checkpoint is read
    family = preset_config(preset).family
    cls = backbone_class(family)
    # The family's Path options name files the import reads: the output must stay clear of them.
    inputs = [folder, *(options.get(o.name) for o in cls.import_options if o.type is Path)]
    check_output(out, overwrite, inputs)  # before reading the checkpoint
    imported = cls.from_original(folder, preset=preset, overrides=overrides, **options)
    if check:
        check_forward(imported.model, torch_device, precision, what=f"the import of {folder}")
    imported.model.save_pretrained(
        out,
        extra_json={"dataset_statistics.json": imported.statistics},
        overwrite=overwrite,
        card_facts={"imported from": str(Path(folder).resolve()), "command": command},
        base_model=str(folder),
        inputs=inputs,
    )
    n_params = sum(p.numel() for p in imported.model.parameters())
    print(f"wrote {out} ({family}, {n_params:,} parameters)")


def check_forward(
    model: VLABackbone, device: torch.device, precision: Precision, what: str
) -> None:
    """One forward of ``model`` on a blank observation (zero images and proprio, shaped by its
    config) on ``device`` under ``precision``: a conversion, device or dtype problem shows here,
    before anything is written, instead of in the first rollout."""
    import torch

    config = model.config
    size = config.image_size
    batch = {
        "images": torch.zeros(1, config.num_images, 3, size, size, device=device),
        "proprio": torch.zeros(1, config.proprio_dim, device=device),
        "instruction": ["pick up the object"],
    }
    model.eval().to(device)
    with torch.no_grad(), precision_context(device, precision)():
        actions = model.predict_action(batch)  # type: ignore[arg-type]  # a Batch's keys
    if not bool(torch.isfinite(actions).all()):
        raise CapVectorError(
            f"{what} gives non-finite actions on {device} ({precision}): the checkpoint or its "
            "conversion is broken, or the precision overflows; try --precision 32-true"
        )


def _add_import_options(parser: ArgumentParser, families: Mapping[str, type[VLABackbone]]) -> None:
    """One argument group per family with its ``import_options``; an option two families declare
    is one flag whose help names both. Absent options are left out of the parsed namespace, so
    the loader's own defaults apply."""
    from capvector.backbones import BackboneError

    added: dict[str, argparse.Action] = {}
    for family, cls in families.items():
        if not cls.import_options:
            continue
        group = parser.add_argument_group(f"options of {family} presets")
        for option in cls.import_options:
            flag = "--" + option.name.replace("_", "-")
            if flag in added:
                added[flag].help = f"{added[flag].help}; {family}: {option.help}"
                continue
            kind = {"action": "store_true"} if option.type is bool else {"type": option.type}
            try:
                added[flag] = group.add_argument(
                    flag, dest=option.name, default=argparse.SUPPRESS, help=option.help, **kind
                )
            except argparse.ArgumentError as err:
                raise BackboneError(
                    f"{cls.__name__}.import_options: {err}; rename the option"
                ) from err


if __name__ == "__main__":
    sys.exit(main())
