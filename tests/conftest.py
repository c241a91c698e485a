"""Shared test helpers: small real HDF5 demo files written with h5py, a quiet CPU ``Trainer``, the
distributed fit script, a local Hugging Face Hub cache, and the ``slow``/``sim`` markers and
the opt-in ``install``/``fullsize`` ones."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py
import lightning as L
import numpy as np
import pytest
import torch

from capvector.backbones import base as backbone_registry
from capvector.data import keys

CAMERAS = ("agentview", "robot0_eye_in_hand")
UPSTREAM_FIXTURES = Path(__file__).parent / "fixtures" / "upstream"
"""Checkpoints and outputs written by the original projects' own code, a folder per family with
its PROVENANCE; read by the family tests in tests/backbones/<family>/."""


def write_demo_file(
    path: Path,
    lengths: tuple[int, ...] = (12, 10),
    image_size: int = 64,
    instruction: str = "lift the red cube",
    seed: int = 0,
) -> Path:
    """A robomimic/LIBERO-layout file with the keys `capvector demos` writes (random content)."""
    rng = np.random.default_rng(seed)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps({"env_name": "Lift", "type": 1, "env_kwargs": {}})
        data.attrs["language_instruction"] = instruction
        data.attrs["total"] = sum(lengths)
        for camera in CAMERAS:
            f_px = image_size / (2 * np.tan(np.deg2rad(45) / 2))
            data.attrs[f"{camera}_intrinsics"] = np.array(
                [[f_px, 0, image_size / 2], [0, f_px, image_size / 2], [0, 0, 1]], dtype=np.float32
            )
        for i, length in enumerate(lengths):
            demo = data.create_group(f"demo_{i}")
            demo.attrs["num_samples"] = length
            actions = rng.uniform(-1, 1, size=(length, 7)).astype(np.float32)
            actions[:, -1] = np.sign(actions[:, -1])
            demo["actions"] = actions
            obs = demo.create_group("obs")
            for camera in CAMERAS:
                obs[f"{camera}_image"] = rng.integers(
                    0, 255, (length, image_size, image_size, 3), dtype=np.uint8
                )
                obs[f"{camera}_depth"] = rng.uniform(
                    0.5, 2.0, (length, image_size, image_size)
                ).astype(np.float32)
            obs["robot0_eef_pos"] = rng.normal(size=(length, 3)).astype(np.float32)
            obs["robot0_eef_axis_angle"] = rng.normal(size=(length, 3)).astype(np.float32)
            obs["robot0_gripper_qpos"] = rng.normal(size=(length, 2)).astype(np.float32)
            demo.create_dataset(
                "annotations",
                data=[f"step {t} of demo {i}" for t in range(length)],
                dtype=h5py.string_dtype(),
            )
    return path


@pytest.fixture
def demo_file(tmp_path: Path) -> Path:
    return write_demo_file(tmp_path / "demos.hdf5")


@pytest.fixture(autouse=True)
def _deterministic() -> None:
    torch.manual_seed(0)
    torch.set_num_threads(1)  # tests run beside each other on 2 cores; avoid oversubscription


FIT_SCRIPT = Path(__file__).with_name("distributed_fit.py")


def run_fit_script(out: Path, data: Path, *args: str) -> list[float]:
    """Run tests/distributed_fit.py for one preset; the per-step global losses."""
    launch_fit_script(out, data, *args)
    return fit_losses(out)


def fit_losses(out: Path) -> list[float]:
    """The per-step global losses a run of tests/distributed_fit.py wrote into ``out``."""
    return json.loads((out / "losses.json").read_text())


def launch_fit_script(out: Path, data: Path, *args: str) -> None:
    """Run tests/distributed_fit.py (Lightning launches the processes).

    A run whose process crashed (a signal, such as SIGSEGV) is run once more from scratch, with a
    warning that carries its stderr: gloo on CPU (torch 2.14.1) crashed once in ~40 CI runs, rank 0
    with SIGSEGV inside FSDP2's full-state-dict gather, and 13 reruns of that fit did not reproduce
    it. A native crash in the collective library, not in our code; a second crash, or any error a
    Python exception reports, fails. ``PYTHONFAULTHANDLER`` (inherited by the ranks Lightning
    starts) prints where a crash was, and marks a crash of rank 1, which rank 0 sees as an error.

    A 1-process run (no ``--devices`` above 1) runs the script's ``main`` in this process instead:
    Lightning launches nothing for it, and a process of its own would only add the ~10 s CPU of
    importing torch, Lightning and capvector again. The script seeds every run itself, so the
    references the 2-process runs are compared with are the same numbers either way."""
    command = [sys.executable, str(FIT_SCRIPT), "--data", str(data), "--out", str(out), *args]
    if devices_of(args) == 1:
        fit_in_this_process(command[2:])
        return
    env = {**os.environ, "PYTHONFAULTHANDLER": "1"}
    for attempt in (1, 2):
        result = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env)
        crashed = result.returncode < 0 or "Fatal Python error" in result.stderr
        if not crashed or attempt == 2:
            break
        warnings.warn(
            f"distributed fit crashed (exit {result.returncode}); running it again. Its stderr "
            f"ended:\n{result.stderr[-3000:]}",
            stacklevel=2,
        )
        shutil.rmtree(out, ignore_errors=True)
    assert result.returncode == 0, result.stderr[-4000:]


def devices_of(args: tuple[str, ...]) -> int:
    """The ``--devices`` a fit script command line asks for (the script's default: 1)."""
    flags = list(args)
    return int(flags[flags.index("--devices") + 1]) if "--devices" in flags else 1


def fit_in_this_process(argv: list[str]) -> None:
    """tests/distributed_fit.py's ``main(argv)`` in this process; the environment variables
    ``L.seed_everything`` sets (``PL_GLOBAL_SEED``, which later subprocesses would inherit) are
    put back."""
    from distributed_fit import main as fit_script

    saved = dict(os.environ)
    try:
        fit_script(argv)
    finally:
        os.environ.clear()
        os.environ.update(saved)


def cpu_trainer(max_steps: int, root: Path | None = None, **overrides: object) -> L.Trainer:
    """A quiet single-process CPU ``Trainer`` for ``max_steps``: no logger, progress bar, model
    summary, checkpoints or validation unless ``overrides`` ask for them."""
    settings: dict = {
        "max_steps": max_steps,
        "accelerator": "cpu",
        "logger": False,
        "enable_progress_bar": False,
        "enable_model_summary": False,
        "enable_checkpointing": False,
        "limit_val_batches": 0,
        "default_root_dir": root,
    }
    return L.Trainer(**{**settings, **overrides})


@contextmanager
def restored_registry() -> Iterator[None]:
    """Backbone families and presets, and benchmark suites, registered inside the block are
    unregistered after it."""
    from capvector.envs.registry import SUITES

    with backbone_registry.FAMILIES.scoped(), backbone_registry.PRESETS.scoped(), SUITES.scoped():
        yield


@pytest.fixture
def scoped_registry() -> Iterator[None]:
    """Undo the test's backbone and suite registrations (they would otherwise outlive it)."""
    with restored_registry():
        yield


def assert_field_changes_the_model(preset: str, overrides: dict, batch: dict) -> None:
    """Changing config ``overrides`` of ``preset`` changes something: the parameters (names or
    shapes), or, on the same weights, the training loss or the predicted actions (same seeds)."""
    from capvector.backbones import build_backbone

    torch.manual_seed(0)
    base = build_backbone(preset).eval()
    changed = build_backbone(preset, **overrides).eval()
    shapes = {k: v.shape for k, v in base.state_dict().items()}
    if shapes != {k: v.shape for k, v in changed.state_dict().items()}:
        return  # an architectural field: it changes the parameters themselves
    changed.load_state_dict(base.state_dict())
    inference = {k: v for k, v in batch.items() if k != keys.ACTIONS}

    def outputs(model: torch.nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            torch.manual_seed(0)
            loss = model(batch).loss
            torch.manual_seed(0)
            return loss, model.predict_action(inference)

    (loss_a, act_a), (loss_b, act_b) = outputs(base), outputs(changed)
    assert not torch.allclose(loss_a, loss_b) or not torch.allclose(act_a, act_b), overrides


def cache_snapshot(cache: Path, repo_id: str, folder: Path) -> Path:
    """``folder``'s files as revision ``main`` of model repo ``repo_id`` in the hub cache
    ``cache``, stored as ``snapshot_download`` stores a download: ``models--org--name/{blobs/
    <sha256>, snapshots/<commit>/<file> -> blob, refs/main}``. huggingface_hub has no public API
    that writes into its cache without a hub, so the layout is written here and
    ``huggingface_hub.scan_cache_dir`` checks it. Returns the snapshot folder."""
    from huggingface_hub import scan_cache_dir

    repo = cache / f"models--{repo_id.replace('/', '--')}"
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    listing = hashlib.sha1()
    for path in files:
        listing.update(path.relative_to(folder).as_posix().encode() + path.read_bytes())
    commit = listing.hexdigest()  # 40 hex digits, as a git commit hash
    snapshot = repo / "snapshots" / commit
    for path in files:
        data = path.read_bytes()
        blob = repo / "blobs" / hashlib.sha256(data).hexdigest()  # an LFS file's etag
        blob.parent.mkdir(parents=True, exist_ok=True)
        blob.write_bytes(data)
        link = snapshot / path.relative_to(folder)
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(commit)
    (cached,) = [r for r in scan_cache_dir(cache).repos if r.repo_id == repo_id]
    (revision,) = cached.revisions
    assert revision.refs == {"main"} and revision.nb_files == len(files), "not huggingface_hub's"
    return snapshot


OPT_IN_MARKERS = ("install", "fullsize", "mini", "referee")


def write_untrained_libero_export(folder: Path) -> Path:
    """An untrained tiny OpenVLA-OFT export that sees LIBERO's agentview at 32 px (rendering
    dominates a LIBERO step on a CPU), with statistics of 7-d actions and 8-d proprio."""
    from capvector.data.spec import DataSpec
    from capvector.data.statistics import compute_statistics
    from capvector.module import VLAModule

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    statistics = compute_statistics(rng.normal(size=(100, 7)), rng.normal(size=(100, 8)), 4)
    spec = DataSpec(cameras=["agentview"], image_size=32, statistics={"capvector": statistics})
    VLAModule(backbone="openvla-oft-tiny", data_spec=spec).export(folder)
    return folder


LONGEST_FILES = [
    "test_install.py", "test_capability_distributed.py", "test_launchers.py", "test_slurm.py",
    "test_libero_experts.py", "test_loggers.py", "test_recipe.py", "test_determinism.py",
    "test_validation_loop.py", "test_distributed.py", "test_libero_render.py", "test_docs.py",
    "test_materialize.py",
]  # fmt: skip
"""The test files that took longest in `make test` (its ``--durations`` list, 2026-12-07)."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Opt-in tests run only when ``-m`` names their marker, not in a plain or a ``-m "not sim"``
    run: the install tests build a fresh environment (minutes; `make test` adds them with
    ``-m "install or not install"``); the ``fullsize`` ones build a full-size preset (≈ 10 GB of
    RAM, minutes; `make test` leaves them out: ``-m fullsize`` runs them); the ``mini`` ones fit
    ``openvla-oft-mini`` in subprocesses (minutes: ``-m mini``); the ``referee`` ones compare
    every LIBERO task with the robosuite 1.4 fixtures (~15 min; ``-m referee``)."""
    named = config.getoption("markexpr")
    opted_out = [m for m in OPT_IN_MARKERS if m not in named]
    kept = [item for item in items if not any(item.get_closest_marker(m) for m in opted_out)]
    if len(kept) < len(items):
        config.hook.pytest_deselected(items=[i for i in items if i not in kept])
        items[:] = kept
    # `make test`'s `--dist loadfile` hands files to its two workers in this order: the longest
    # first, so that none of them starts last and runs alone at the end (a stable sort: the
    # tests of a file keep their order).
    first = {name: rank for rank, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: first.get(item.path.name, len(first)))
