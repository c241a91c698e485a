"""capvector.vectors: merge into export folders and apply_vector_ in memory."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from capvector.io.outputs import MARKER
from capvector.vectors import (
    CapabilityVector,
    CapVectorError,
    LoraFactors,
    apply_vector_,
    extract,
    load_vector,
    merge,
    validate_vector,
)
from capvector.vectors.merge import MERGE_RECORD
from capvector.vectors.vector import VectorFolder
from test_vectors_common import TinyVLA, finetune, tiny_state, write_export


def _export_state(folder: Path) -> dict[str, torch.Tensor]:
    state: dict[str, torch.Tensor] = {}
    for f in sorted(folder.glob("*.safetensors")):
        state.update(load_file(str(f)))
    return state


@pytest.fixture
def setup(tmp_path: Path) -> dict:
    pre = tiny_state(0)
    models = {
        "pre": pre,
        "aux": finetune(pre, 1),
        "sft": finetune(pre, 2),
        "aux2": finetune(pre, 3),
    }
    paths = {name: write_export(tmp_path / name, s, shards=2) for name, s in models.items()}
    extract(paths["aux"], paths["sft"], tmp_path / "c1")
    extract(paths["aux2"], paths["sft"], tmp_path / "c2", include=["*.layers.0.*"])
    return {"models": models, "paths": paths, "tmp": tmp_path}


def test_merge_equals_state_dict_arithmetic(setup) -> None:
    tmp, models, paths = setup["tmp"], setup["models"], setup["paths"]
    record = merge(paths["pre"], [(tmp / "c1", 0.7), (tmp / "c2", -0.3)], tmp / "meta")

    c1, c2 = load_vector(tmp / "c1"), load_vector(tmp / "c2")
    merged = _export_state(tmp / "meta")
    assert set(merged) == set(models["pre"])
    for key, base in models["pre"].items():
        expected = base.clone()
        if key in c1:
            expected = expected + 0.7 * c1.dense[key]
        if key in c2:
            expected = expected - 0.3 * c2.dense[key]
        torch.testing.assert_close(merged[key], expected, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(
        merged["action_head.model.fc1.weight"],
        models["pre"]["action_head.model.fc1.weight"],
        rtol=0,
        atol=0,
    )

    # Same sharding; every non-weight file copied byte for byte.
    base_files = sorted(p.relative_to(paths["pre"]) for p in paths["pre"].rglob("*") if p.is_file())
    out_files = sorted(
        p.relative_to(tmp / "meta") for p in (tmp / "meta").rglob("*") if p.is_file()
    )
    assert out_files == sorted({*base_files, Path(MERGE_RECORD), Path("README.md"), Path(MARKER)})
    rewritten = {"model.safetensors.index.json", "config.json", "README.md"}
    for rel in base_files:
        if rel.suffix != ".safetensors" and rel.name not in rewritten:
            assert (tmp / "meta" / rel).read_bytes() == (paths["pre"] / rel).read_bytes()
    # config.json gains the record of merged vectors; the model card says what was merged.
    config = json.loads((tmp / "meta" / "config.json").read_text())
    assert config.pop("merged_vectors") == [
        {
            **{k: v for k, v in r.items() if k in ("fingerprint", "path")},
            "scale": s,
            "by": "capvector merge",
        }
        for r, s in zip(record["vectors"], (0.7, -0.3), strict=True)
    ]
    assert config == json.loads((paths["pre"] / "config.json").read_text())
    card = (tmp / "meta" / "README.md").read_text()
    assert card.startswith("---\nlibrary_name: capvector\n")  # a local base: named in the body
    assert "base_model:" not in card and f"| {paths['pre'].resolve()} |" in card
    assert all(v["fingerprint"][:27] in card for v in record["vectors"])
    index = json.loads((tmp / "meta" / "model.safetensors.index.json").read_text())
    assert (
        index["weight_map"]
        == json.loads((paths["pre"] / "model.safetensors.index.json").read_text())["weight_map"]
    )
    assert [v["scale"] for v in record["vectors"]] == [0.7, -0.3]
    assert json.loads((tmp / "meta" / MERGE_RECORD).read_text())["base"] == record["base"]
    # The record holds each vector's fingerprint as recorded when it was written.
    assert [v["fingerprint"] for v in record["vectors"]] == [
        json.loads((tmp / name / "capability_vector.json").read_text())["fingerprint"]
        for name in ("c1", "c2")
    ]


def test_merge_of_a_peft_lora_folder_matches_merge_and_unload(tmp_path: Path) -> None:
    from peft import LoraConfig, PeftModel, get_peft_model

    pre = tiny_state(0)
    base = write_export(tmp_path / "pre", pre)
    model = TinyVLA()
    model.load_state_dict(pre)
    config = LoraConfig(
        r=4,
        lora_alpha=12,
        target_modules=["q_proj", "down_proj", "embed_tokens"],
        rank_pattern={"down_proj": 2},
        alpha_pattern={"down_proj": 5},
        use_rslora=True,
    )
    peft_model = get_peft_model(model, config)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name, p in peft_model.named_parameters():
            if "lora_" in name:
                p.copy_(0.2 * torch.randn(p.shape, generator=g))
    peft_model.save_pretrained(str(tmp_path / "adapter"), save_embedding_layers=False)

    merge(base, [(tmp_path / "adapter", 1.0)], tmp_path / "meta")
    ours = _export_state(tmp_path / "meta")
    fresh = TinyVLA()
    fresh.load_state_dict(pre)
    theirs = (
        PeftModel.from_pretrained(fresh, str(tmp_path / "adapter")).merge_and_unload().state_dict()
    )
    changed = 0
    for key, value in theirs.items():
        torch.testing.assert_close(ours[key], value, rtol=1e-5, atol=1e-6)
        changed += not torch.equal(value, pre[key])
    assert changed == 2 * 2 + 1  # q_proj and down_proj of two layers, and the embedding


def test_merge_of_a_lowrank_vector_matches_peft(tmp_path: Path) -> None:
    from peft import PeftModel

    pre = tiny_state(0)
    paths = [write_export(tmp_path / n, finetune(pre, s)) for n, s in (("aux", 1), ("sft", 2))]
    base = write_export(tmp_path / "pre", pre)
    extract(*paths, tmp_path / "vec", rank=3, full_rank=["*embed_tokens*"])
    merge(base, [(tmp_path / "vec", 1.0)], tmp_path / "meta")
    ours = _export_state(tmp_path / "meta")
    model = TinyVLA()
    model.load_state_dict(pre)
    theirs = PeftModel.from_pretrained(model, str(tmp_path / "vec")).merge_and_unload().state_dict()
    full = load_vector(tmp_path / "vec").dense
    for key, value in theirs.items():
        # peft merges the adapter; the full-rank part (biases, norms, embeddings) is ours alone.
        expected = value + full[key] if key in full else value
        torch.testing.assert_close(ours[key], expected, rtol=1e-5, atol=1e-6)


def test_merge_refuses_mismatched_or_broken_vectors(setup) -> None:
    tmp, paths = setup["tmp"], setup["paths"]
    no_head = {k: v for k, v in setup["models"]["pre"].items() if not k.startswith("action_head")}
    small_base = write_export(tmp / "small", no_head)
    extract(paths["aux"], paths["sft"], tmp / "with_head", include=["*"])
    with pytest.raises(
        CapVectorError,
        match=r"has 4 tensor\(s\) the base .* lacks, e.g. `action_head.*--exclude 'action_head\.\*'",
    ):
        merge(small_base, [(tmp / "with_head", 1.0)], tmp / "out")

    wrong = tmp / "wrong"
    wrong.mkdir()
    save_file(
        {"language_model.model.norm.weight": torch.ones(3)},
        str(wrong / "capability_vector.safetensors"),
    )
    with pytest.raises(
        CapVectorError, match=r"1 shape mismatch.*language_model.model.norm.weight: vector \(3,\)"
    ):
        merge(paths["pre"], [(wrong, 1.0)], tmp / "out")

    nan = tmp / "nan"
    nan.mkdir()
    bad = load_vector(tmp / "c1").dense
    last = sorted(bad)[-1]
    bad[last] = torch.full_like(bad[last], float("inf"))
    save_file(bad, str(nan / "capability_vector.safetensors"))
    with pytest.raises(
        CapVectorError, match=rf"merging `{last}` gives NaN/Inf: vector .*nan has NaN/Inf"
    ):
        merge(paths["pre"], [(nan, 1.0)], tmp / "out")
    with pytest.raises(CapVectorError, match="is not a vector folder.*model export"):
        merge(paths["pre"], [(paths["aux"], 1.0)], tmp / "out")
    with pytest.raises(CapVectorError, match="finite"):
        merge(paths["pre"], [(tmp / "c1", float("nan"))], tmp / "out")
    assert not (tmp / "out").exists()
    assert not [p for p in tmp.iterdir() if p.name.startswith(".")]


def test_apply_vector_matches_merge_bit_for_bit(setup) -> None:
    tmp, models, paths = setup["tmp"], setup["models"], setup["paths"]
    merge(paths["pre"], [(tmp / "c1", 0.5)], tmp / "meta")
    merged = _export_state(tmp / "meta")

    model = TinyVLA()
    model.load_state_dict(models["pre"])
    changed = apply_vector_(model, tmp / "c1", scale=0.5)
    assert len(changed) == len(VectorFolder(tmp / "c1"))
    for key, value in model.state_dict().items():
        assert torch.equal(value, merged[key]), key

    state = {k: v.clone() for k, v in models["pre"].items()}
    apply_vector_(state, load_vector(tmp / "c1"), scale=0.5)
    for key, value in state.items():
        assert torch.equal(value, merged[key]), key


def test_apply_vector_finds_peft_base_layer_names(setup) -> None:
    from peft import LoraConfig, inject_adapter_in_model

    tmp, models = setup["tmp"], setup["models"]
    model = TinyVLA()
    model.load_state_dict(models["pre"])
    model = inject_adapter_in_model(LoraConfig(r=2, target_modules=["q_proj", "up_proj"]), model)
    names = dict(model.named_parameters())
    assert "language_model.model.layers.0.self_attn.q_proj.base_layer.weight" in names
    vector = load_vector(tmp / "c1")
    changed = apply_vector_(model, vector, scale=1.0)
    assert "language_model.model.layers.0.self_attn.q_proj.base_layer.weight" in changed
    key = "language_model.model.layers.0.self_attn.q_proj.weight"
    torch.testing.assert_close(
        names["language_model.model.layers.0.self_attn.q_proj.base_layer.weight"],
        models["pre"][key] + vector.dense[key],
        rtol=0,
        atol=0,
    )


def test_apply_vector_validates_everything_before_changing_anything(setup) -> None:
    models = setup["models"]
    model = TinyVLA()
    model.load_state_dict(models["pre"])
    before = {k: v.clone() for k, v in model.state_dict().items()}
    good = load_vector(setup["tmp"] / "c1").dense
    # Each bad tensor sorts after good ones, so applying before validating would show.
    cases = {
        "the model lacks": {**good, "zzz.extra.weight": torch.ones(2)},
        "shape mismatch": {**good, "language_model.model.norm.weight": torch.ones(3)},
        "NaN/Inf": {**good, "language_model.model.norm.weight": torch.full((16,), float("nan"))},
        "only floating tensors": {
            **good,
            "language_model.model.position_ids": torch.ones(8, dtype=torch.int64),
        },
    }
    for message, vector in cases.items():
        with pytest.raises(CapVectorError, match=message):
            validate_vector(model, vector)
        with pytest.raises(CapVectorError):
            apply_vector_(model, vector)
        for key, value in model.state_dict().items():
            assert torch.equal(value, before[key]), (message, key)
    with pytest.raises(CapVectorError, match="finite"):
        apply_vector_(model, good, scale=float("inf"))


def test_apply_lowrank_vector_in_memory(setup) -> None:
    models = setup["models"]
    key = "language_model.model.layers.1.mlp.up_proj.weight"
    b, a = torch.randn(24, 2), torch.randn(2, 16)
    vector = CapabilityVector(lowrank={key: LoraFactors(b, a, scale=0.5)})
    state = {k: v.clone() for k, v in models["pre"].items()}
    apply_vector_(state, vector, scale=2.0)
    torch.testing.assert_close(state[key], models["pre"][key] + b @ a, rtol=1e-6, atol=1e-6)


def test_apply_vector_to_dtensor_parameters(tmp_path: Path) -> None:
    import torch.distributed as dist
    from torch.distributed.device_mesh import init_device_mesh
    from torch.distributed.tensor import Shard, distribute_tensor

    if not dist.is_available():
        pytest.skip("torch.distributed is not available")
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'rdzv'}", rank=0, world_size=1)
    try:
        mesh = init_device_mesh("cpu", (1,))
        layer = torch.nn.Linear(6, 4)
        base = layer.weight.detach().clone()
        layer.weight = torch.nn.Parameter(
            distribute_tensor(layer.weight.detach(), mesh, [Shard(0)])
        )
        delta = torch.randn(4, 6)
        apply_vector_(layer, {"weight": delta}, scale=0.5)
        torch.testing.assert_close(
            layer.weight.full_tensor(), base + 0.5 * delta, rtol=1e-6, atol=1e-6
        )
    finally:
        dist.destroy_process_group()


def test_merge_reports_how_much_of_the_vector_bf16_keeps(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """A vector small next to the weights mostly rounds away in bf16: `capvector merge` measures
    ‖(round(θ+λc) − round(θ)) − λc‖ / ‖λc‖, warns naming the worst tensors, and keeps all of it with
    --dtype float32. apply_vector_ (the callback's merge) measures the same thing."""
    from capvector.cli import main
    from capvector.vectors import apply_vector_
    from capvector.vectors.precision import MergePrecision

    pre = tiny_state(0)
    bf16 = {k: v.to(torch.bfloat16) if v.is_floating_point() else v for k, v in pre.items()}
    write_export(tmp_path / "pre", bf16)
    write_export(tmp_path / "sft", pre)
    write_export(tmp_path / "aux", finetune(pre, 1, scale=1e-4))  # |c| ≈ 1e-4 against weights ≈ 0.1
    assert extract(aux=tmp_path / "aux", sft=tmp_path / "sft", out=tmp_path / "vec")["norm"] > 0
    base = ["merge", "--base", str(tmp_path / "pre"), "--vector", str(tmp_path / "vec")]
    assert main([*base, "--out", str(tmp_path / "bf16")]) == 0
    err = capsys.readouterr().err
    record = json.loads((tmp_path / "bf16" / MERGE_RECORD).read_text())["precision"]
    assert record["dtype"] == "bfloat16" and record["relative_error"] > 0.1
    assert "warning" in err and record["worst"][0]["tensor"] in err and "--dtype float32" in err

    assert main([*base, "--out", str(tmp_path / "fp32"), "--dtype", "float32"]) == 0
    record = json.loads((tmp_path / "fp32" / MERGE_RECORD).read_text())["precision"]
    assert record["dtype"] == "float32" and record["relative_error"] < 1e-3
    assert all(
        t.dtype == torch.float32
        for t in load_file(tmp_path / "fp32" / "model.safetensors").values()
        if t.is_floating_point()
    )
    assert "warning" not in capsys.readouterr().err

    in_memory = MergePrecision()
    apply_vector_(bf16, tmp_path / "vec", 1.0, precision=in_memory)
    bf16_record = json.loads((tmp_path / "bf16" / MERGE_RECORD).read_text())["precision"]
    assert in_memory.relative_error() == pytest.approx(bf16_record["relative_error"], rel=1e-6)


def test_apply_vector_holds_a_block_of_rows_not_copies_of_the_whole_tensor() -> None:
    """The in-memory merge (MergeCapabilityVector's) of a low-rank vector into a large bf16 weight
    works a block of rows at a time, and skips tensors the vector leaves at zero. Whole, the
    float32 delta and the precision check's float32 and float64 copies were ~16× a bf16 tensor:
    with Pi0.5's 257 k × 2,048 embedding that OOM-killed a 24 GiB host. A fresh interpreter's
    high-water mark above the model, against the weight's size."""
    import subprocess
    import sys

    script = (
        "import resource, torch\n"
        "from capvector.vectors import apply_vector_\n"
        "from capvector.vectors.lowrank import LoraFactors\n"
        "from capvector.vectors.precision import MergePrecision\n"
        "from capvector.vectors.vector import CapabilityVector\n"
        "big = torch.nn.Linear(2048, 65536, bias=False, dtype=torch.bfloat16)\n"  # 256 MiB
        "zero = torch.nn.Linear(2048, 65536, bias=False, dtype=torch.bfloat16)\n"
        "model = torch.nn.ModuleDict({'big': big, 'zero': zero}).requires_grad_(False)\n"
        "factors = LoraFactors(torch.randn(65536, 4), torch.randn(4, 2048))\n"
        "nothing = LoraFactors(torch.zeros(65536, 1), torch.zeros(1, 2048))\n"
        "vector = CapabilityVector({}, {'big.weight': factors, 'zero.weight': nothing})\n"
        "before = zero.weight.clone()\n"
        "base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "changed = apply_vector_(model, vector, 1e-3, precision=MergePrecision())\n"
        "grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) * 1024\n"
        "assert changed == ['big.weight'] and torch.equal(zero.weight, before), changed\n"
        "print(grown / big.weight.nbytes)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    # Measured 1.37× (a 32 MiB block's float32 and float64 temporaries); whole tensors: 16.3×.
    assert float(out.stdout) < 3.0
