"""Hub ids wherever a folder is taken, read from a local hub cache with ``HF_HUB_OFFLINE=1``, and
``capvector push`` up to the network (no hub is reachable here: the upload itself is untested)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from huggingface_hub import ModelCard, constants

from capvector.backbones import build_backbone, from_pretrained
from capvector.cli import main
from capvector.errors import CapVectorError
from capvector.io.hub import hub_id
from capvector.io.modelcard import read_model_card
from capvector.workflows.push import upload_plan
from conftest import cache_snapshot

ROOT = Path(__file__).resolve().parents[1]
THETA_PRE = ROOT / "assets" / "theta_pre"
REPO = "capvector-test/tiny"


@pytest.fixture
def hub_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """θ_pre as hub repo ``capvector-test/tiny`` in a hub cache under ``tmp_path``, the hub
    offline. huggingface_hub read HF_HUB_CACHE and HF_HUB_OFFLINE when first imported; its
    constants are what it reads from then on, so this process sets those, subprocesses the env."""
    cache = tmp_path / "hub"
    cache_snapshot(cache, REPO, THETA_PRE)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    for name, value in {
        "HF_HOME": tmp_path / "hf",
        "HF_HUB_CACHE": cache,
        "HF_HUB_OFFLINE": 1,
    }.items():
        monkeypatch.setenv(name, str(value))
    return cache


def test_a_hub_id_loads_from_the_local_cache_offline(
    hub_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    hubbed, local = from_pretrained(REPO), from_pretrained(THETA_PRE)
    for (name, a), (_, b) in zip(
        hubbed.state_dict().items(), local.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), name
    # A fine-tune from it names the hub id as base_model; a missing repo is one clear line.
    from capvector.module import VLAModule

    VLAModule(pretrained=REPO).export(tmp_path / "tuned")
    assert read_model_card(tmp_path / "tuned").data.base_model == [REPO]
    with pytest.raises(CapVectorError, match="not in the hub cache .* HF_HUB_OFFLINE is set"):
        from_pretrained("capvector-test/missing")
    # A local folder wins over a hub id of the same spelling, as in transformers.
    (tmp_path / "capvector-test").mkdir()
    monkeypatch.chdir(tmp_path)
    assert hub_id(REPO) == REPO and hub_id("capvector-test") is None
    (tmp_path / "capvector-test" / "tiny").mkdir()
    assert hub_id(REPO) is None


@pytest.mark.sim
def test_evaluate_takes_a_hub_id_offline(hub_cache: Path, tmp_path: Path) -> None:
    """``capvector evaluate --ckpt capvector-test/tiny`` as a user runs it: HF_HUB_CACHE and
    HF_HUB_OFFLINE=1 in the environment of a fresh process."""
    out = tmp_path / "eval.json"
    done = subprocess.run(
        [sys.executable, "-m", "capvector.cli", "evaluate", "--ckpt", REPO, "--task", "Lift",
         "--episodes", "1", "--max-steps", "8", "--batch-size", "1", "--workers", "0",
         "--device", "cpu", "--json", str(out)],
        cwd=tmp_path, env={**os.environ, "MUJOCO_GL": "egl", "OMP_NUM_THREADS": "1"},
        capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    (row,) = json.loads(out.read_text())
    assert row["episodes"] == 1 and row["per_episode"][0]["steps"] == 8
    # Its output a pipe, not a terminal: progress lines instead of a bar's redraws.
    assert re.search(r"^evaluating: 1/1 episodes, 0 succeeded, \d+ (s|min)$", done.stderr, re.M)
    assert "episode/s" not in done.stderr


def test_vectors_from_hub_ids_name_them_as_base_model_and_paths_in_the_body(
    hub_cache: Path, tmp_path: Path
) -> None:
    sft = build_backbone("openvla-oft-tiny")
    sft.load_state_dict(from_pretrained(THETA_PRE).state_dict())
    with torch.no_grad():
        next(sft.parameters()).add_(1e-2)
    sft.save_pretrained(tmp_path / "sft")
    extract = ["extract", "--aux", REPO, "--sft", str(tmp_path / "sft"), "--out"]
    assert main([*extract, str(tmp_path / "vec")]) == 0
    card = read_model_card(tmp_path / "vec")
    assert card.data.base_model == [REPO]
    assert str((tmp_path / "sft").resolve()) in card.text  # the local source, in the body


def test_push_plans_every_file_and_a_valid_card_then_stops_at_the_network(
    hub_cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    kind, operations = upload_plan(THETA_PRE)
    files = sorted(p.relative_to(THETA_PRE).as_posix() for p in THETA_PRE.iterdir())
    assert kind == "export" and [op.path_in_repo for op in operations] == files
    for op in operations:
        assert Path(op.path_or_fileobj).read_bytes() == (THETA_PRE / op.path_in_repo).read_bytes()
    card = ModelCard((THETA_PRE / "README.md").read_text())
    assert card.data.library_name == "capvector" and card.data.pipeline_tag == "robotics"

    vector = ROOT / "assets" / "capability_vector"
    kind, operations = upload_plan(vector)
    assert kind == "vector"
    assert {op.path_in_repo for op in operations} == {
        p.relative_to(vector).as_posix() for p in vector.rglob("*") if p.is_file()
    }
    assert main(["push", str(vector), "org/vec", "--dry-run"]) == 0
    assert "task_vector_aux/README.md" in capsys.readouterr().out

    # The network is where it stops: offline, one line and exit code 2, nothing half-done.
    assert main(["push", str(THETA_PRE), "org/theta"]) == 2
    assert "could not upload to org/theta" in capsys.readouterr().err


def test_push_refuses_a_card_with_a_local_base_model(tmp_path: Path) -> None:
    build_backbone("openvla-oft-tiny").save_pretrained(tmp_path / "export")
    readme = tmp_path / "export" / "README.md"
    _, header, body = readme.read_text().split("---\n", 2)
    meta = {**yaml.safe_load(header), "base_model": ["/home/me/runs/theta_pre"]}
    readme.write_text(f"---\n{yaml.safe_dump(meta)}---\n{body}")
    with pytest.raises(CapVectorError, match="base_model '/home/me/runs/theta_pre'.*repo ids only"):
        upload_plan(tmp_path / "export")
    assert main(["push", str(tmp_path / "export"), "not a repo"]) == 2
    readme.unlink()
    with pytest.raises(CapVectorError, match="has no README.md"):
        upload_plan(tmp_path / "export")


def test_a_hub_id_with_a_revision_is_a_valid_base_model_and_hub_vectors_are_named_by_id(
    hub_cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from huggingface_hub.utils import validate_repo_id

    # A fine-tune of REPO@main: base_model is the repo id the hub validates, the revision is
    # kept in the body.
    from capvector.module import VLAModule

    VLAModule(pretrained=f"{REPO}@main").export(tmp_path / "tuned")
    card = read_model_card(tmp_path / "tuned")
    assert card.data.base_model == [REPO]
    validate_repo_id(card.data.base_model[0])
    assert f"| base model revision | {REPO}@main |" in card.text

    # A merge of a vector given by hub id names it by that id, not its cache snapshot folder.
    cache_snapshot(hub_cache, "capvector-test/vec", ROOT / "assets" / "capability_vector")
    out = tmp_path / "meta"
    assert main(["merge", "--base", str(THETA_PRE), "--vector", "capvector-test/vec@main:1",
                 "--out", str(out)]) == 0  # fmt: skip
    text = read_model_card(out).text
    assert (
        "c(capvector-test/vec@main)" in text and "| vector 1 | capvector-test/vec@main x 1 " in text
    )
    assert str(hub_cache) not in text

    # A card written with the revision in base_model (as before) is refused by our check and by
    # push --dry-run, as the hub would refuse it.
    readme = tmp_path / "tuned" / "README.md"
    _, header, body = readme.read_text().split("---\n", 2)
    meta = {**yaml.safe_load(header), "base_model": [f"{REPO}@main"]}
    readme.write_text(f"---\n{yaml.safe_dump(meta)}---\n{body}")
    with pytest.raises(CapVectorError, match=f"base_model '{REPO}@main'.*not a hub repo id"):
        upload_plan(tmp_path / "tuned")
    capsys.readouterr()
    assert main(["push", str(tmp_path / "tuned"), "org/tuned", "--dry-run"]) == 2
    assert f"base_model '{REPO}@main'" in capsys.readouterr().err
