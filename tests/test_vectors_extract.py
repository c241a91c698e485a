"""capvector.vectors: extract (exports, checkpoints, low-rank/PEFT), errors and atomic output."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from capvector.vectors import CapVectorError, VectorFolder, extract, load_vector, svd_factors
from test_vectors_common import (
    FFN,
    HIDDEN,
    TinyVLA,
    finetune,
    tiny_state,
    write_checkpoint,
    write_export,
)


def _read_vector(folder: Path) -> dict[str, torch.Tensor]:
    vector = VectorFolder(folder)
    return {k: vector.read(k) for k in vector}


def _leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


@pytest.fixture
def models(tmp_path: Path) -> dict[str, dict[str, torch.Tensor]]:
    pre = tiny_state(0)
    return {"pre": pre, "aux": finetune(pre, 1), "sft": finetune(pre, 2)}


def test_extract_equals_state_dict_difference_on_sharded_exports(tmp_path: Path, models) -> None:
    aux = write_export(tmp_path / "aux", models["aux"], shards=3)
    sft = write_export(tmp_path / "sft", models["sft"])
    # A small shard size forces a sharded vector with an index.
    meta = extract(aux, sft, tmp_path / "vec", max_shard_size=4096)

    assert (tmp_path / "vec" / "capability_vector.safetensors.index.json").is_file()
    vector = _read_vector(tmp_path / "vec")
    expected = {
        k
        for k, v in models["aux"].items()
        if k.startswith("language_model.") and v.is_floating_point()
    }
    assert set(vector) == expected  # default include = capability_parameters: no action head
    for key in expected:
        torch.testing.assert_close(
            vector[key], models["aux"][key] - models["sft"][key], rtol=0, atol=0
        )
        assert meta["tensors"][key]["norm"] == pytest.approx(float(vector[key].norm()), rel=1e-6)
    assert meta["format"] == "capvector-vector"
    assert meta["include"] == ["language_model.*"]
    assert meta["skipped"]["not_floating"] == ["language_model.model.position_ids"]
    assert meta["sources"]["aux"] == {
        "path": str(aux.resolve()), "kind": "export", "family": "tiny", "preset": "tiny-test"
    }  # fmt: skip
    # Hashed while written, the same when read back (one read of the files).
    assert meta["fingerprint"] == VectorFolder(tmp_path / "vec").fingerprint()
    assert meta["fingerprint"].startswith("tensors-sha256:")
    assert meta["norm"] == pytest.approx(
        math.sqrt(sum(float(v.double().square().sum()) for v in vector.values())), rel=1e-6
    )
    assert meta["storage"] == "full" and meta["dtype"] == "float32"


def test_extract_include_exclude_and_base_task_vectors(tmp_path: Path, models) -> None:
    paths = {name: write_export(tmp_path / name, state) for name, state in models.items()}
    extract(
        paths["aux"],
        paths["sft"],
        tmp_path / "vec",
        base=paths["pre"],
        include=["*"],
        exclude=["*.layers.1.*"],
        objectives=["spatial_alignment"],
    )
    vector = _read_vector(tmp_path / "vec")
    assert "action_head.model.fc1.weight" in vector
    assert not any(".layers.1." in k for k in vector)
    for sub, run in (("task_vector_aux", "aux"), ("task_vector_sft", "sft")):
        tv = _read_vector(tmp_path / "vec" / sub)
        assert set(tv) == set(vector)
        for key in tv:
            torch.testing.assert_close(
                tv[key], models[run][key] - models["pre"][key], rtol=0, atol=0
            )
        meta = json.loads((tmp_path / "vec" / sub / "capability_vector.json").read_text())
        assert meta["kind"] == "task_vector" and meta["definition"] == f"{run} - base"
    meta = json.loads((tmp_path / "vec" / "capability_vector.json").read_text())
    assert meta["objectives"] == ["spatial_alignment"]
    assert meta["task_vectors"] == ["task_vector_aux", "task_vector_sft"]
    assert set(meta["sources"]) == {"aux", "sft", "base"}


def _lora_backbone(state: dict[str, torch.Tensor], seed: int) -> nn.Module:
    from peft import LoraConfig, inject_adapter_in_model

    model = TinyVLA()
    model.load_state_dict(state)
    config = LoraConfig(
        r=4, lora_alpha=8, target_modules=["q_proj", "v_proj", "up_proj", "embed_tokens"]
    )
    model = inject_adapter_in_model(config, model)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "lora_" in name:  # peft initialises B to 0; a trained adapter is not
                p.copy_(0.1 * torch.randn(p.shape, generator=g))
    return model


def _peft_merged_state(model: nn.Module) -> dict[str, torch.Tensor]:
    from peft.tuners.lora import LoraLayer

    for module in model.modules():
        if isinstance(module, LoraLayer):
            module.merge()
    out = {}
    for key, value in model.state_dict().items():
        if "lora_" not in key:
            out[key.replace(".base_layer.", ".")] = value.clone()
    return out


def test_checkpoint_with_lora_reads_like_its_merged_export(tmp_path: Path, models) -> None:
    aux_model = _lora_backbone(models["aux"], seed=3)
    sft_model = _lora_backbone(models["sft"], seed=4)
    lora = {"r": 4, "alpha": 8.0, "scaling": 2.0}
    aux_ckpt = write_checkpoint(tmp_path / "aux.ckpt", aux_model.state_dict(), lora)
    sft_ckpt = write_checkpoint(tmp_path / "sft.ckpt", sft_model.state_dict(), lora)
    # The same weights merged by peft itself, as exports.
    aux_export = write_export(tmp_path / "aux", _peft_merged_state(aux_model))
    sft_export = write_export(tmp_path / "sft", _peft_merged_state(sft_model))

    from_ckpt = extract(aux_ckpt, sft_ckpt, tmp_path / "from_ckpt")
    extract(aux_export, sft_export, tmp_path / "from_export")
    a, b = _read_vector(tmp_path / "from_ckpt"), _read_vector(tmp_path / "from_export")
    assert set(a) == set(b)
    assert "language_model.model.layers.0.self_attn.q_proj.weight" in a
    assert not any("lora_" in k or "base_layer" in k or k.startswith("objectives") for k in a)
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6)
    assert from_ckpt["sources"]["aux"]["kind"] == "checkpoint"
    assert from_ckpt["objectives"] == ["alignment"]  # from the checkpoint's objectives.* keys


def test_input_errors_name_the_tensors(tmp_path: Path, models) -> None:
    aux = write_export(tmp_path / "aux", models["aux"])
    other_caps = write_export(tmp_path / "other", models["sft"], capability_parameters=["*"])
    with pytest.raises(CapVectorError, match="disagree on capability_parameters"):
        extract(aux, other_caps, tmp_path / "out")

    bigger = tiny_state(5, layers=3)
    bigger["language_model.model.embed_tokens.weight"] = torch.zeros(40, HIDDEN)
    grown = write_export(tmp_path / "grown", bigger)
    with pytest.raises(CapVectorError, match=r"differ in shape for 1 tensor.*embed_tokens"):
        extract(aux, grown, tmp_path / "out")

    sft = write_export(tmp_path / "sft", models["sft"])
    no_head = {k: v for k, v in models["pre"].items() if not k.startswith("action_head")}
    base = write_export(tmp_path / "base", no_head)
    with pytest.raises(
        CapVectorError,
        match=r"θ_aux has 4 tensor\(s\) the base lacks.*`action_head.model.fc1.bias`.*--exclude 'action_head\.\*'",
    ):
        extract(aux, sft, tmp_path / "out", base=base, include=["*"])

    with pytest.raises(CapVectorError, match="match none"):
        extract(aux, sft, tmp_path / "out", include=["vision_backbone.*"])
    with pytest.raises(CapVectorError, match="either --rank or --energy"):
        extract(aux, sft, tmp_path / "out", rank=2, energy=0.9)
    assert not (tmp_path / "out").exists()

    extract(aux, sft, tmp_path / "out")
    with pytest.raises(CapVectorError, match="exists; choose another --out or pass --overwrite"):
        extract(aux, sft, tmp_path / "out")
    extract(aux, sft, tmp_path / "out", include=["*.norm.*"], overwrite=True)
    assert set(_read_vector(tmp_path / "out")) == {
        "language_model.model.norm.weight",
        "language_model.model.norm.bias",
    }


def test_truncated_or_corrupted_input_is_a_clear_error(tmp_path: Path, models) -> None:
    aux = write_export(tmp_path / "aux", models["aux"], shards=2)
    sft = write_export(tmp_path / "sft", models["sft"])
    shard = aux / "model-00002-of-00002.safetensors"
    shard.write_bytes(shard.read_bytes()[:-100])
    with pytest.raises(
        CapVectorError, match="model-00002-of-00002.safetensors is not a readable safetensors file"
    ):
        extract(aux, sft, tmp_path / "vec")
    ckpt = tmp_path / "bad.ckpt"
    ckpt.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CapVectorError, match="cannot read checkpoint"):
        extract(ckpt, sft, tmp_path / "vec")
    assert not (tmp_path / "vec").exists()
    assert _leftovers(tmp_path) == []


def test_nan_found_late_leaves_no_partial_output(tmp_path: Path, models) -> None:
    aux_state = dict(models["aux"])
    last = sorted(
        k
        for k in aux_state
        if k.startswith("language_model.") and k != "language_model.model.position_ids"
    )[-1]
    aux_state[last] = aux_state[last].clone()
    aux_state[last].view(-1)[-1] = float("nan")
    aux = write_export(tmp_path / "aux", aux_state)
    sft = write_export(tmp_path / "sft", models["sft"])
    base = write_export(tmp_path / "pre", models["pre"])
    out = tmp_path / "runs" / "vec"
    with pytest.raises(CapVectorError, match=rf"`{last}` in aux .* NaN/Inf"):
        extract(aux, sft, out, base=base, max_shard_size=2048)
    assert not out.exists()
    assert _leftovers(out.parent) == []  # the temporary sibling folder is gone too


def test_full_rank_adapter_loads_in_peft_and_reproduces_the_vector(tmp_path: Path, models) -> None:
    from peft import PeftModel

    aux = write_export(tmp_path / "aux", models["aux"])
    sft = write_export(tmp_path / "sft", models["sft"])
    meta = extract(aux, sft, tmp_path / "vec", rank=64, full_rank=["*embed_tokens*"])
    vector = load_vector(tmp_path / "vec")
    tensors = meta["tensors"]
    assert tensors["language_model.model.layers.0.mlp.up_proj.weight"]["storage"] == "lora"
    assert tensors["language_model.model.layers.0.mlp.up_proj.weight"]["rank"] == HIDDEN
    assert tensors["language_model.model.embed_tokens.weight"]["storage"] == "full"
    assert tensors["language_model.model.layers.0.self_attn.q_proj.bias"]["storage"] == "full"
    assert tensors["language_model.model.norm.weight"]["storage"] == "full"
    assert all(
        t["retained_energy"] == pytest.approx(1.0)
        for t in tensors.values()
        if t["storage"] == "lora"
    )

    config = json.loads((tmp_path / "vec" / "adapter_config.json").read_text())
    assert config["lora_alpha"] == config["r"] == HIDDEN
    assert "language_model.model.layers.1.self_attn.q_proj" in config["target_modules"]

    model = TinyVLA()
    model.load_state_dict(models["pre"])
    merged = PeftModel.from_pretrained(model, str(tmp_path / "vec")).merge_and_unload().state_dict()
    for key in vector.lowrank:
        expected = models["pre"][key] + models["aux"][key] - models["sft"][key]
        torch.testing.assert_close(merged[key], expected, rtol=1e-5, atol=1e-5)
    for key in vector.dense:  # full tensors live in capability_vector.safetensors
        torch.testing.assert_close(vector.dense[key], models["aux"][key] - models["sft"][key])
    unchanged = "language_model.model.layers.0.self_attn.q_proj.bias"
    torch.testing.assert_close(merged[unchanged], models["pre"][unchanged], rtol=0, atol=0)


def test_energy_picks_per_layer_ranks_that_peft_loads(tmp_path: Path) -> None:
    from peft import PeftModel

    pre = tiny_state(0)
    aux, sft = dict(pre), dict(pre)
    g = torch.Generator().manual_seed(7)
    spectra = {  # singular values of each layer's delta: energy 0.9 needs 1, 2 and 3 components
        "language_model.model.layers.0.mlp.up_proj.weight": [10.0, 1.0, 1.0, 1.0],
        "language_model.model.layers.0.mlp.down_proj.weight": [3.0, 3.0, 1.0, 0.5],
        "language_model.model.layers.1.mlp.up_proj.weight": [2.0, 2.0, 2.0, 0.1],
    }
    for key, sigma in spectra.items():
        out, inp = pre[key].shape
        u, _ = torch.linalg.qr(torch.randn(out, 4, generator=g))
        v, _ = torch.linalg.qr(torch.randn(inp, 4, generator=g))
        aux[key] = pre[key] + u @ torch.diag(torch.tensor(sigma)) @ v.T
    paths = [write_export(tmp_path / n, s) for n, s in (("aux", aux), ("sft", sft))]
    meta = extract(*paths, tmp_path / "vec", include=list(spectra), energy=0.9)
    for (key, sigma), rank in zip(spectra.items(), (1, 2, 3), strict=True):
        power = torch.tensor(sigma) ** 2
        assert meta["tensors"][key]["rank"] == rank
        assert meta["tensors"][key]["retained_energy"] == pytest.approx(
            float(power[:rank].sum() / power.sum()), rel=1e-5
        )
    config = json.loads((tmp_path / "vec" / "adapter_config.json").read_text())
    assert config["r"] == 3 and len(config["rank_pattern"]) == 2

    model = TinyVLA()
    model.load_state_dict(pre)
    merged = PeftModel.from_pretrained(model, str(tmp_path / "vec")).merge_and_unload().state_dict()
    for key in spectra:
        rank = meta["tensors"][key]["rank"]
        delta = aux[key] - pre[key]
        u, s, vh = torch.linalg.svd(delta)
        best = u[:, :rank] @ torch.diag(s[:rank]) @ vh[:rank]  # Eckart–Young: the best rank-k fit
        torch.testing.assert_close(merged[key], pre[key] + best, rtol=1e-4, atol=1e-5)


def test_svd_factors_truncation_keeps_the_expected_energy() -> None:
    torch.manual_seed(0)
    delta = torch.randn(FFN, HIDDEN)
    factors, retained = svd_factors(delta, rank=5)
    s = torch.linalg.svdvals(delta).double()
    assert factors.rank == 5
    assert retained == pytest.approx(float((s[:5] ** 2).sum() / (s**2).sum()), rel=1e-6)
    residual = delta - factors.rows()
    assert float(residual.double().square().sum()) == pytest.approx(
        float((s[5:] ** 2).sum()), rel=1e-4
    )
    assert factors.norm_sq() == pytest.approx(float((s[:5] ** 2).sum()), rel=1e-5)
    zero, kept = svd_factors(torch.zeros(4, 3), energy=0.5)
    assert zero.rank == 1 and kept == 1.0 and float(zero.rows().abs().sum()) == 0.0


def test_randomized_svd_finds_the_exact_top_rank_of_a_low_rank_delta_with_noise() -> None:
    """What a 7 B extraction meets: θ_aux − θ_sft of two LoRA fits, rank ≤ 2r, plus bf16
    rounding noise. The range finder gives the exact SVD's rank-k fit to within the noise, the
    same bits on every call, and refuses an energy rule it cannot evaluate."""
    g = torch.Generator().manual_seed(3)
    signal = torch.randn(96, 8, generator=g) @ torch.randn(8, 200, generator=g)
    delta = signal + 1e-4 * torch.randn(96, 200, generator=g)
    exact, exact_kept = svd_factors(delta, rank=6)
    fast, fast_kept = svd_factors(delta, rank=6, method="randomized")
    best = float((delta - exact.rows()).double().square().sum())
    found = float((delta - fast.rows()).double().square().sum())
    assert found == pytest.approx(best, rel=1e-3) and fast.rank == 6
    assert fast_kept == pytest.approx(exact_kept, rel=1e-6)
    again, _ = svd_factors(delta, rank=6, method="randomized")
    assert torch.equal(again.lora_a, fast.lora_a) and torch.equal(again.lora_b, fast.lora_b)
    with pytest.raises(ValueError, match="fixed rank"):
        svd_factors(delta, energy=0.9, method="randomized")
    zero, kept = svd_factors(torch.zeros(96, 200), rank=6, method="randomized")
    assert kept == 1.0 and zero.rank == 1 and not zero.lora_a.any() and not zero.lora_b.any()


def test_the_randomized_svd_holds_little_beside_a_large_delta() -> None:
    """Its ‖delta‖² is summed block by block: it used to square a whole float64 copy, 4× the
    float32 delta (8 GiB on Pi0.5's embedding). A fresh interpreter's high-water mark; the old
    code grows by 4× the delta here, the range finder itself by a few columns."""
    import subprocess
    import sys

    script = (
        "import resource, torch\n"
        "from capvector.vectors.lowrank import svd_factors\n"
        "d = torch.randn(32768, 32) @ torch.randn(32, 2048)\n"  # 0.25 GiB
        "base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "svd_factors(d, rank=32, method='randomized')\n"
        "print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) * 1024 / d.nbytes)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert float(out.stdout) < 0.5


def test_squared_norm_sums_blocks_in_float64() -> None:
    from capvector.io.tensors import squared_norm

    delta = torch.randn(1000, 37, generator=torch.Generator().manual_seed(0))
    whole = float(delta.double().square().sum())
    assert squared_norm(delta, chunk_elements=640) == pytest.approx(whole, rel=1e-12)
    assert squared_norm(torch.tensor(3.0)) == 9.0


def test_extract_with_the_randomized_svd_records_it_and_loads_in_peft(
    tmp_path: Path, models
) -> None:
    from capvector.cli import main

    aux = write_export(tmp_path / "aux", models["aux"])
    sft = write_export(tmp_path / "sft", models["sft"])
    with pytest.raises(CapVectorError, match="--svd randomized finds a fixed --rank"):
        extract(aux, sft, tmp_path / "vec", energy=0.9, svd="randomized")
    out = tmp_path / "vec"
    args = ["extract", "--aux", str(aux), "--sft", str(sft), "--out", str(out), "--rank", "2"]
    assert main([*args, "--svd", "randomized"]) == 0
    meta = json.loads((out / "capability_vector.json").read_text())
    assert meta["lowrank"]["svd"] == "randomized"
    exact = extract(aux, sft, tmp_path / "exact", rank=2)
    for key, tensor in meta["tensors"].items():
        if tensor["storage"] == "lora":
            assert tensor["retained_energy"] == pytest.approx(
                exact["tensors"][key]["retained_energy"], rel=1e-4
            ), key
    assert load_vector(out).keys() == load_vector(tmp_path / "exact").keys()


def test_bf16_inputs_give_a_bf16_vector_computed_in_float32(tmp_path: Path) -> None:
    torch.manual_seed(0)
    a = {"language_model.w": torch.randn(8, 8).bfloat16()}
    b = {"language_model.w": torch.randn(8, 8).bfloat16()}
    for name, state in (("a", a), ("b", b)):
        (tmp_path / name).mkdir()
        save_file(state, str(tmp_path / name / "model.safetensors"))
    meta = extract(tmp_path / "a", tmp_path / "b", tmp_path / "vec")
    assert meta["dtype"] == "bfloat16"
    got = load_file(str(tmp_path / "vec" / "capability_vector.safetensors"))["language_model.w"]
    assert got.dtype == torch.bfloat16
    assert torch.equal(
        got, (a["language_model.w"].float() - b["language_model.w"].float()).bfloat16()
    )
    extract(tmp_path / "a", tmp_path / "b", tmp_path / "vec32", dtype="float32")
    got32 = load_file(str(tmp_path / "vec32" / "capability_vector.safetensors"))["language_model.w"]
    assert torch.equal(got32, a["language_model.w"].float() - b["language_model.w"].float())


@pytest.mark.parametrize("preset", ["openvla-oft-tiny", "pi05-tiny"])
def test_default_lowrank_vector_loads_in_plain_peft_like_capvector_merge(
    preset: str, tmp_path: Path
) -> None:
    """The README's snippet: ``PeftModel.from_pretrained(from_pretrained(BASE), DIR)`` then
    ``merge_and_unload()`` adds exactly the adapter's part of ``capvector merge --base BASE
    --vector DIR`` (embeddings included, as peft's embedding LoRA) with no peft warning; the
    tensors stored in full complete it."""
    import warnings

    from peft import PeftModel

    from capvector.backbones import build_backbone, from_pretrained
    from capvector.cli import main
    from capvector.vectors import apply_vector_

    model = build_backbone(preset)
    model.save_pretrained(tmp_path / "base")
    model.save_pretrained(tmp_path / "sft")
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1e-2 * torch.randn_like(p))
    model.save_pretrained(tmp_path / "aux")
    folders = {name: str(tmp_path / name) for name in ("base", "sft", "aux", "vec", "merged")}
    assert main(["extract", "--aux", folders["aux"], "--sft", folders["sft"], "--out", folders["vec"], "--rank", "4"]) == 0  # fmt: skip
    adapter = load_file(tmp_path / "vec" / "adapter_model.safetensors")
    assert any(k.endswith("lora_embedding_A") for k in adapter)
    assert main(["merge", "--base", folders["base"], "--vector", folders["vec"], "--out", folders["merged"]]) == 0  # fmt: skip

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        peft_model = PeftModel.from_pretrained(from_pretrained(folders["base"]), folders["vec"])
        merged_by_peft = peft_model.merge_and_unload()
    assert not [w for w in caught if "peft" in w.filename or "lora" in str(w.message).lower()]
    expected = from_pretrained(folders["merged"]).state_dict()
    base = from_pretrained(folders["base"]).state_dict()
    vector = VectorFolder(tmp_path / "vec")
    in_adapter = {k for k in vector if vector.storage(k) == "lora"}
    ours = merged_by_peft.state_dict()
    assert ours.keys() == expected.keys()
    for key in expected:
        want = expected[key] if key in in_adapter else base[key]
        torch.testing.assert_close(ours[key], want, rtol=0, atol=1e-6, msg=key)
    apply_vector_(merged_by_peft, vector.load_outside_adapter())
    ours = merged_by_peft.state_dict()
    worst = max(float((ours[k] - expected[k]).abs().max()) for k in expected)
    assert worst <= 1e-6, worst
