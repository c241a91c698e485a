"""``capvector export`` (a Lightning checkpoint to an export folder) and ``capvector
import-original`` (an original project's checkpoint to an export folder)."""

from __future__ import annotations

import argparse
import shlex
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capvector.errors import CapVectorError
from capvector.eval.device import Precision, precision_context, resolve_device, resolve_precision
from capvector.io.outputs import check_output
from capvector.tool_cli import Tool, run_tool

if TYPE_CHECKING:
    import torch
    from jsonargparse import ArgumentParser

    from capvector.backbones import VLABackbone


def export_main(argv: list[str]) -> int:
    return run_tool(export_cli, argv, "export")


def export_cli(ckpt: str, out: str, overwrite: bool = False, dtype: str | None = None) -> None:
    """Export a Lightning checkpoint to a folder that `extract`, `merge` and `evaluate` read.

    Args:
        ckpt: Lightning checkpoint (.ckpt)
        out: output folder (written atomically)
        overwrite: replace an existing --out
        dtype: of every floating tensor written: float32, bfloat16 or float16 (default: the
            base's, the fit's model.frozen_dtype; float32 keeps a short fit's update unrounded)
    """
    from capvector.io.weights import parse_dtype
    from capvector.module import load_module

    if dtype is not None:
        parse_dtype(dtype)  # before loading the checkpoint
    check_output(out, overwrite, [ckpt], folder=True)  # before loading the checkpoint
    folder = load_module(ckpt).export(out, overwrite=overwrite, dtype=dtype)
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
    check_output(out, overwrite, inputs, folder=True)  # before reading the checkpoint
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
