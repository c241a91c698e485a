"""capvector.vectors: compose (sum, TIES), inspect, and the CLI entry points."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from capvector.cli import main
from capvector.vectors import CapVectorError, compose, extract, inspect_vector, load_vector
from capvector.vectors.compose import ties, trim
from capvector.vectors.inspect import group_of
from capvector.workflows.inspection import main as inspect_main
from capvector.workflows.vectors import compose_main, extract_main, merge_main, parse_size
from test_vectors_common import finetune, tiny_state, write_export


def _vector_folder(folder: Path, tensors: dict[str, torch.Tensor]) -> Path:
    folder.mkdir(parents=True)
    save_file(tensors, str(folder / "capability_vector.safetensors"))
    return folder


def test_trim_keeps_the_largest_magnitudes() -> None:
    x = torch.tensor([0.1, -5.0, 2.0, -0.2, 3.0])
    assert torch.equal(trim(x, 0.4), torch.tensor([0.0, -5.0, 0.0, 0.0, 3.0]))
    assert torch.equal(trim(x, 0.01), torch.tensor([0.0, -5.0, 0.0, 0.0, 0.0]))  # at least one
    assert torch.equal(trim(x, 1.0), x)


def test_ties_elects_signs_and_takes_the_disjoint_mean() -> None:
    deltas = torch.tensor(
        [
            [1.0, -2.0, 3.0, 0.0],
            [3.0, 1.0, -1.0, 0.5],
            [-1.0, -4.0, 2.0, 0.0],
        ]
    )
    # density 1: no trim. Column by column, with the elected sign = sign of the column sum:
    #   0: sum 3 > 0 -> mean of 1, 3 = 2;  1: sum -5 -> mean of -2, -4 = -3
    #   2: sum 4 -> mean of 3, 2 = 2.5;    3: sum 0.5 -> only 0.5 agrees (zeros never vote) = 0.5
    assert torch.equal(
        ties(deltas, [1.0, 1.0, 1.0], density=1.0), torch.tensor([2.0, -3.0, 2.5, 0.5])
    )
    # Weights scale the contributions and the divisor: column 0 -> (2·1 + 1·3) / (2 + 1).
    weighted = ties(deltas, [2.0, 1.0, 1.0], density=1.0)
    assert weighted[0] == pytest.approx(5 / 3)
    # Trim to the top half of each row first: row 0 keeps -2, 3; row 1 keeps 3 and one of ±1 (the
    # tie does not change the result); row 2 keeps -4, 2.
    trimmed = ties(deltas, [1.0, 1.0, 1.0], density=0.5)
    assert torch.equal(trimmed, torch.tensor([3.0, -3.0, 2.5, 0.0]))
    counted = ties(torch.tensor([[1.0], [1.0], [-5.0]]), [1.0, 1.0, 1.0], 1.0, consensus="count")
    assert torch.equal(counted, torch.tensor([1.0]))  # two positive votes beat one large negative


def test_compose_sum_and_ties_folders(tmp_path: Path) -> None:
    a = {
        "language_model.w": torch.tensor([[1.0, -2.0], [3.0, 0.5]]),
        "language_model.b": torch.tensor([1.0]),
    }
    b = {
        "language_model.w": torch.tensor([[3.0, 1.0], [-1.0, 0.0]]),
        "language_model.b": torch.tensor([-3.0]),
    }
    pa, pb = _vector_folder(tmp_path / "a", a), _vector_folder(tmp_path / "b", b)

    meta = compose([pa, pb], tmp_path / "sum", weights=[0.5, 2.0])
    summed = load_vector(tmp_path / "sum").dense
    for key in a:
        torch.testing.assert_close(summed[key], 0.5 * a[key] + 2.0 * b[key])
    assert meta["method"] == "sum" and meta["weights"] == [0.5, 2.0]
    assert len(meta["sources"]["vectors"]) == 2

    compose([pa, pb], tmp_path / "ties", method="ties", density=1.0)
    merged = load_vector(tmp_path / "ties").dense
    torch.testing.assert_close(merged["language_model.w"], torch.tensor([[2.0, -2.0], [3.0, 0.5]]))
    torch.testing.assert_close(merged["language_model.b"], torch.tensor([-3.0]))

    _vector_folder(tmp_path / "c", {"language_model.w": torch.zeros(2, 2)})
    with pytest.raises(CapVectorError, match=r"covers other tensors.*`language_model.b`"):
        compose([pa, tmp_path / "c"], tmp_path / "bad")
    with pytest.raises(CapVectorError, match="unknown --method"):
        compose([pa, pb], tmp_path / "bad", method="average")
    assert not (tmp_path / "bad").exists()


def test_inspect_groups_by_layer_and_compares(tmp_path: Path) -> None:
    pre = tiny_state(0)
    paths = {
        n: write_export(tmp_path / n, finetune(pre, s))
        for n, s in (("aux", 1), ("sft", 2), ("x", 3))
    }
    extract(paths["aux"], paths["sft"], tmp_path / "c")
    extract(paths["x"], paths["sft"], tmp_path / "d", rank=4)
    c = load_vector(tmp_path / "c")
    d = load_vector(tmp_path / "d")

    report = inspect_vector(
        tmp_path / "c", against=tmp_path / "d", plot=tmp_path / "plots" / "norms.png"
    )
    layer0 = next(g for g in report.groups if g.name == "language_model.model.layers.0")
    keys0 = [k for k in c if k.startswith("language_model.model.layers.0.")]
    assert layer0.tensors == len(keys0) and layer0.layer == 0
    assert layer0.norm == pytest.approx(
        sum(float(c.delta(k).double().square().sum()) for k in keys0) ** 0.5, rel=1e-9
    )
    dot = sum(float((c.delta(k).double() * d.delta(k).double()).sum()) for k in keys0)
    other = sum(float(d.delta(k).double().square().sum()) for k in keys0) ** 0.5
    assert layer0.cosine == pytest.approx(dot / (layer0.norm * other), rel=1e-6)
    dots = sum(float((c.delta(k).double() * d.delta(k).double()).sum()) for k in c)
    norms = [sum(float(v.delta(k).double().square().sum()) for k in c) ** 0.5 for v in (c, d)]
    assert report.cosine == pytest.approx(dots / (norms[0] * norms[1]), rel=1e-6)
    assert report.lowrank_tensors == 0 and report.shared_tensors == len(c)
    assert (tmp_path / "plots" / "norms.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| language_model.model.layers.1 |" in report.table()
    assert inspect_vector(tmp_path / "c", against=tmp_path / "c").cosine == pytest.approx(1.0)

    assert group_of("vision_backbone.blocks.11.attn.qkv.weight") == (
        "vision_backbone.blocks.11",
        "vision_backbone.blocks",
        11,
    )
    assert group_of("projector.fc1.weight") == ("projector.fc1", None, None)


def test_cli_round_trip_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pre = tiny_state(0)
    paths = {n: write_export(tmp_path / n, finetune(pre, s)) for n, s in (("aux", 1), ("sft", 2))}
    base = write_export(tmp_path / "pre", pre, shards=2)
    vec, meta = tmp_path / "vec", tmp_path / "meta"

    assert (
        extract_main(
            [
                "--aux",
                str(paths["aux"]),
                "--sft",
                str(paths["sft"]),
                "--out",
                str(vec),
                "--exclude",
                "*.norm.*",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert f"wrote {vec}" in out and "skipped 1 tensor(s) not floating" in out
    assert merge_main(["--base", str(base), "--vector", f"{vec}:0.5", "--out", str(meta)]) == 0
    assert "0.5·" in capsys.readouterr().out
    assert (meta / "model.safetensors.index.json").is_file()
    assert (
        compose_main(
            ["--vectors", str(vec), str(vec), "--method", "ties", "--out", str(tmp_path / "t")]
        )
        == 0
    )
    assert (
        inspect_main(
            [str(vec), "--against", str(tmp_path / "t"), "--plot", str(tmp_path / "p.png")]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "| **total** |" in printed and "cosine with" in printed

    # Errors (through `capvector`, which prints them): message on stderr, no traceback, exit
    # code 2, nothing written.
    assert main(["merge", "--base", str(base), "--vector", str(vec), "--out", str(meta)]) == 2
    err = capsys.readouterr().err
    assert "exists; choose another --out or pass --overwrite" in err and "Traceback" not in err
    no_head = write_export(
        tmp_path / "nohead", {k: v for k, v in pre.items() if not k.startswith("action_head")}
    )
    extract_main(
        [
            "--aux",
            str(paths["aux"]),
            "--sft",
            str(paths["sft"]),
            "--out",
            str(tmp_path / "all"),
            "--include",
            "*",
        ]
    )
    capsys.readouterr()
    assert (
        main(
            [
                "merge",
                "--base",
                str(no_head),
                "--vector",
                str(tmp_path / "all"),
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 2
    )
    assert "--exclude 'action_head.*'" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert json.loads((vec / "capability_vector.json").read_text())["exclude"] == ["*.norm.*"]


def test_parse_size() -> None:
    assert parse_size("2GB") == 2 * 10**9
    assert parse_size("1.5GiB") == int(1.5 * 2**30)
    assert parse_size("4096") == 4096
