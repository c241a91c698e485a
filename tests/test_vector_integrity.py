"""The merge record cannot be fooled: a vector's fingerprint hashes every tensor (recorded when the
vector is written, checked when it is read for a merge or a resume), its JSON is guarded by its own
digest and checked against the weight files, and λ and all-zero vectors are checked. Bad input at
the command line is one line, exit code 2, no output, and the inputs byte for byte as they were."""

from __future__ import annotations

import json
import re
import shutil
import struct
from pathlib import Path

# Lightning binds its log handler to the stderr of the moment it is imported (see test_cli_errors).
import lightning.pytorch  # noqa: F401
import pytest
import torch

from capvector.backbones import build_backbone
from capvector.callbacks import MergeCapabilityVector
from capvector.cli import main
from capvector.data.datamodule import RobotDataModule
from capvector.errors import CapVectorError
from capvector.module import VLAModule
from capvector.vectors import VectorFolder, compose, extract, merge
from capvector.workflows.sweep import sweep
from conftest import cpu_trainer, write_demo_file
from test_capability_callbacks import merge_fit
from test_cli_errors import tree_digest
from test_vectors_common import finetune, tiny_state, write_export

WEIGHTS, META = "capability_vector.safetensors", "capability_vector.json"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two openvla-oft-tiny exports, c = aux − sft, θ_meta = sft + c, and demos."""
    root = tmp_path_factory.mktemp("integrity")
    model = build_backbone("openvla-oft-tiny")
    model.save_pretrained(root / "sft")
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1e-3 * torch.randn_like(p))
    model.save_pretrained(root / "aux")
    extract(root / "aux", root / "sft", root / "vector")
    merge(root / "sft", [(root / "vector", 1.0)], root / "meta")
    write_demo_file(root / "demos.hdf5")
    return root


def copy_vector(inputs: Path, to: Path) -> Path:
    shutil.copytree(inputs / "vector", to)
    return to


def edit_outside_the_old_samples(weights: Path) -> None:
    """Add 1 to a float32 value that the former fingerprint (header, then 64 KiB at the start of the
    data, in the middle and at the end of the file) never read."""
    data = bytearray(weights.read_bytes())
    data_start, size, window = 8 + struct.unpack_from("<Q", data)[0], len(data), 64 * 1024
    offset = data_start + (size - data_start) // 16 * 4
    sampled = [data_start, (data_start + size) // 2, size - window]
    assert all(not start <= offset < start + window for start in sampled)
    (value,) = struct.unpack_from("<f", data, offset)
    struct.pack_into("<f", data, offset, value + 1.0)
    weights.write_bytes(data)


def edit_json(folder: Path, change) -> None:  # noqa: ANN001 - a function of the metadata dict
    meta = json.loads((folder / META).read_text())
    change(meta)
    (folder / META).write_text(json.dumps(meta, indent=2))


def assert_refused(
    args: list[str], message: str, inputs: list[Path], out: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """``capvector ARGS`` exits 2 with one error line matching ``message``, leaves the empty folder
    ``out`` (where ARGS write) empty, temporary folders included, and every input as it was."""
    out.mkdir()
    before = [tree_digest(root) for root in inputs]
    try:
        code = main(args)
    except SystemExit as exit_info:
        code = exit_info.code
    errors = [line for line in capfd.readouterr().err.splitlines() if "error" in line]
    assert code == 2
    assert len(errors) == 1 and errors[0].startswith("capvector "), errors
    assert re.search(message, errors[0]), errors[0]
    assert not list(out.iterdir()), sorted(out.rglob("*"))
    assert [tree_digest(root) for root in inputs] == before


def merge_args(base: Path, vector: str, out: Path, *extra: str) -> list[str]:
    return ["merge", "--base", str(base), "--vector", vector, "--out", str(out / "m"), *extra]


# -- the fingerprint -------------------------------------------------------------------------


def test_the_fingerprint_is_recorded_at_write_and_ignores_the_file_layout(tmp_path: Path) -> None:
    pre = tiny_state(0)
    aux = write_export(tmp_path / "aux", finetune(pre, 1), shards=3)
    sft = write_export(tmp_path / "sft", finetune(pre, 2))
    one = extract(aux, sft, tmp_path / "one")
    sharded = extract(aux, sft, tmp_path / "sharded", max_shard_size=4096)
    lowrank = extract(aux, sft, tmp_path / "lowrank", rank=2)
    assert (tmp_path / "sharded" / "capability_vector.safetensors.index.json").is_file()
    assert one["fingerprint"] == sharded["fingerprint"] != lowrank["fingerprint"]
    for name, meta in (("one", one), ("sharded", sharded), ("lowrank", lowrank)):
        assert VectorFolder(tmp_path / name).fingerprint() == meta["fingerprint"]
    summed = compose([tmp_path / "one", tmp_path / "lowrank"], tmp_path / "sum")
    assert VectorFolder(tmp_path / "sum").fingerprint() == summed["fingerprint"]


@pytest.mark.parametrize("edit", ["a value outside the old samples", "the adapter's lora_alpha"])
def test_edited_tensors_are_refused_not_taken_for_the_merged_vector(
    edit: str, inputs: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """θ_meta holds c; a vector whose tensors changed since it was written is not c, and is not
    merged either: the sampled fingerprint called it "already held"."""
    edited = tmp_path / "edited"
    if edit == "the adapter's lora_alpha":  # the scale of low-rank factors is part of c
        extract(inputs / "aux", inputs / "sft", edited, rank=2)
        merge(inputs / "sft", [(edited, 1.0)], tmp_path / "meta")
        config = json.loads((edited / "adapter_config.json").read_text())
        (edited / "adapter_config.json").write_text(json.dumps({**config, "lora_alpha": 4}))
        base = tmp_path / "meta"
    else:
        edit_outside_the_old_samples(copy_vector(inputs, edited) / WEIGHTS)
        base = inputs / "meta"
    assert_refused(
        merge_args(base, str(edited), tmp_path / "out"),
        rf"vector {edited}: its tensors changed since it was written .*extract the vector again",
        [inputs, edited],
        tmp_path / "out",
        capfd,
    )


def test_a_reindented_json_is_the_same_vector(
    inputs: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """Only the JSON's formatting changed: the same fingerprint, so θ_meta already holds it."""
    same = copy_vector(inputs, tmp_path / "reindented")
    meta = json.loads((same / META).read_text())
    (same / META).write_text(json.dumps(meta, indent=7, sort_keys=True, ensure_ascii=False))
    assert VectorFolder(same).fingerprint() == meta["fingerprint"]
    assert_refused(
        merge_args(inputs / "meta", str(same), tmp_path / "out"),
        r"already holds vector .*--allow-repeat",
        [inputs, same],
        tmp_path / "out",
        capfd,
    )


def test_a_resume_checks_the_vector_by_content(inputs: Path, tmp_path: Path) -> None:
    """Fit with c merged at fit start; a resume with c's JSON re-indented goes on, one with a value
    of c changed (where the sampled fingerprint never looked) stops before anything changes."""
    vector = copy_vector(inputs, tmp_path / "vector")
    merge_fit(inputs / "sft", str(vector), inputs / "demos.hdf5", 1, tmp_path / "a")
    ckpt = tmp_path / "a" / "last.ckpt"
    meta = json.loads((vector / META).read_text())
    (vector / META).write_text(json.dumps(meta, indent=1))
    resumed = merge_fit(inputs / "sft", str(vector), inputs / "demos.hdf5", 2, tmp_path / "b", ckpt)
    assert [r.fingerprint for r in resumed.merged_vectors] == [meta["fingerprint"]]
    edit_outside_the_old_samples(vector / WEIGHTS)
    saved = ckpt.read_bytes()
    with pytest.raises(CapVectorError, match=r"its tensors changed since it was written"):
        merge_fit(inputs / "sft", str(vector), inputs / "demos.hdf5", 2, tmp_path / "c", ckpt)
    assert ckpt.read_bytes() == saved


# -- what the JSON claims ----------------------------------------------------------------------

FIRST = "language_model.lm_head.weight"
JSON_EDITS = {
    "another family": (
        lambda m: m["sources"]["aux"].update(family="pi05"),
        r"capability_vector.json was edited after the vector was written .*family, preset",
    ),
    "another preset": (
        lambda m: m["sources"]["sft"].update(preset="openvla-oft-7b"),
        r"capability_vector.json was edited after the vector was written",
    ),
    "another shape": (
        lambda m: m["tensors"][FIRST].update(shape=[64, 320]),
        rf"does not describe this folder's weight files .*{re.escape(FIRST)}: shape \[64, 320\] "
        r"in the JSON, \[320, 64\] in the weights",
    ),
    "another shape, in a JSON without a digest": (
        lambda m: [m.pop("metadata_sha256"), m["tensors"][FIRST].update(shape=[64, 320])],
        r"does not describe this folder's weight files",
    ),
    "another fingerprint": (
        lambda m: m.update(fingerprint="tensors-sha256:" + "0" * 64),
        r"capability_vector.json was edited after the vector was written",
    ),
}


@pytest.mark.parametrize("edit", sorted(JSON_EDITS))
def test_a_json_edited_to_claim_something_else_is_refused(
    edit: str, inputs: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    change, message = JSON_EDITS[edit]
    assert FIRST in json.loads((inputs / "vector" / META).read_text())["tensors"]
    edited = copy_vector(inputs, tmp_path / "edited")
    edit_json(edited, change)
    assert_refused(
        merge_args(inputs / "sft", str(edited), tmp_path / "out"),
        message,
        [inputs, edited],
        tmp_path / "out",
        capfd,
    )


def test_vectors_and_records_from_before_content_fingerprints(
    inputs: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """A vector whose JSON records no fingerprint gets it computed from its tensors (the one a new
    extraction records); a record entry with a sampled fingerprint is matched by its path."""
    legacy = copy_vector(inputs, tmp_path / "legacy")
    edit_json(legacy, lambda m: [m.pop("fingerprint"), m.pop("metadata_sha256")])
    record = merge(inputs / "sft", [(legacy, 1.0)], tmp_path / "meta")
    fingerprint = json.loads((inputs / "vector" / META).read_text())["fingerprint"]
    assert record["vectors"][0]["fingerprint"] == fingerprint
    old_base = tmp_path / "old_meta"
    shutil.copytree(inputs / "meta", old_base)
    config = json.loads((old_base / "config.json").read_text())
    config["merged_vectors"] = [
        {"fingerprint": "sha256:" + "ab" * 32, "scale": 1.0, "path": str(legacy.resolve()),
         "by": "capvector merge"}
    ]  # fmt: skip
    (old_base / "config.json").write_text(json.dumps(config))
    assert_refused(
        merge_args(old_base, str(legacy), tmp_path / "out"),
        r"already holds vector",
        [inputs, legacy, old_base],
        tmp_path / "out",
        capfd,
    )


# -- λ and zero vectors --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "scale,message",
    [
        ("1e39", r"λ = 1e\+39 for .* overflows float32"),
        ("101", r"λ = 101 for .* is outside \[-100, 100\].*--allow-large-scale"),
        ("-1e3", r"λ = -1000 for .* is outside \[-100, 100\]"),
        ("nan", r"λ for .* is nan; it must be a finite number"),
    ],
)
def test_merge_refuses_a_scale_out_of_range(
    scale: str, message: str, inputs: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    args = merge_args(inputs / "sft", f"{inputs / 'vector'}:{scale}", tmp_path / "out")
    assert_refused(args, message, [inputs], tmp_path / "out", capfd)


def test_a_large_scale_merges_when_allowed(inputs: Path, tmp_path: Path) -> None:
    args = merge_args(inputs / "sft", f"{inputs / 'vector'}:150", tmp_path, "--allow-large-scale")
    assert main(args) == 0
    assert json.loads((tmp_path / "m" / "config.json").read_text())["merged_vectors"][0][
        "scale"
    ] == pytest.approx(150)


def test_the_callback_and_the_sweep_check_the_scale_before_any_work(
    inputs: Path, tmp_path: Path
) -> None:
    dm = RobotDataModule(train_files=[str(inputs / "demos.hdf5")], batch_size=4)
    module = VLAModule(pretrained=str(inputs / "sft"), data_spec=dm.spec)
    before = {k: v.clone() for k, v in module.state_dict().items()}
    for scale, message in ((1e39, "overflows float32"), (-500.0, "outside")):
        callback = MergeCapabilityVector(str(inputs / "vector"), scale=scale)
        with pytest.raises(CapVectorError, match=message):
            cpu_trainer(1, tmp_path, callbacks=[callback]).fit(module, dm)
    assert all(torch.equal(v, module.state_dict()[k]) for k, v in before.items())
    with pytest.raises(CapVectorError, match=r"λ = 1000 for .*--allow-large-scale"):
        sweep(str(inputs / "sft"), str(inputs / "vector"), [0.5, 1e3], str(tmp_path / "sweep"))
    assert not (tmp_path / "sweep").exists()


def test_merge_refuses_a_zero_vector(
    inputs: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    zero = tmp_path / "zero"
    compose([inputs / "vector", inputs / "vector"], zero, weights=[1.0, -1.0])
    assert_refused(
        merge_args(inputs / "sft", str(zero), tmp_path / "out"),
        rf"vector {zero} is all zeros .*were aux and sft the same export\?",
        [inputs, zero],
        tmp_path / "out",
        capfd,
    )


@pytest.mark.parametrize("how", ["the same folder", "a byte-identical copy"])
def test_extract_refuses_identical_aux_and_sft(
    how: str, inputs: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    if how == "the same folder":
        sft, message = inputs / "aux", r"--aux and --sft are the same"
    else:
        sft = tmp_path / "copy"
        shutil.copytree(inputs / "aux", sft)
        message = (
            r"identical in all \d+ extracted tensors: c would be all zeros.*Nothing was written"
        )
    out = tmp_path / "out"
    args = ["extract", "--aux", str(inputs / "aux"), "--sft", str(sft), "--out", str(out / "v")]
    assert_refused(args, message, [inputs, sft], out, capfd)
