"""Wall time and peak memory of ``capvector extract`` and ``capvector merge`` on multi-GB models.

Builds three synthetic sharded export folders (θ_pre, θ_aux, θ_sft) of ``--size-gb`` each, with
Llama-7B-shaped tensors (embed 32000×4096, q/k/v/o 4096×4096, gate/up 11008×4096, down 4096×11008),
then runs each stage in a fresh subprocess that reports its own peak RSS (VmHWM):

- ``import torch``: the floor every stage pays (the interpreter and torch's libraries);
- ``baseline``: read both inputs with ``safetensors.torch.load_file`` (touching every byte) and
  write one of them with ``save_file``, shard by shard;
- ``extract``: c = θ_aux − θ_sft (the vector's fingerprint is hashed as it is written);
- ``merge``: θ_pre + c (c's fingerprint is checked first: one more read of the vector);
- ``read vector``: one plain read of the vector's files, the baseline of
- ``fingerprint``: ``VectorFolder.fingerprint()``, the hash of every tensor of the vector.

Targets: peak RSS ≤ 1 GB and wall time ≤ 2× the baseline (extract, merge). Inputs are freshly written, so every stage
reads from the page cache; outputs are fsynced in every stage (the baseline too), and dirty
pages are flushed (``sync``) before each stage.

    python benchmarks/bench_vectors.py [--size-gb 2] [--dtype float32] [--workdir /work/tmp]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HIDDEN, FFN, VOCAB = 4096, 11008, 32000
SHARD_BYTES = 1_000_000_000
NAMES = ("pre", "aux", "sft")


def layout(size_bytes: int, itemsize: int) -> list[tuple[str, tuple[int, ...]]]:
    """Tensor names and shapes of a Llama-like model of at least ``size_bytes``."""
    tensors: list[tuple[str, tuple[int, ...]]] = [
        ("language_model.model.embed_tokens.weight", (VOCAB, HIDDEN))
    ]
    total, layer = VOCAB * HIDDEN * itemsize, 0
    while total < size_bytes:
        prefix = f"language_model.model.layers.{layer}"
        block = [
            (f"{prefix}.self_attn.{p}.weight", (HIDDEN, HIDDEN))
            for p in ("q_proj", "k_proj", "v_proj", "o_proj")
        ]
        block += [
            (f"{prefix}.mlp.gate_proj.weight", (FFN, HIDDEN)),
            (f"{prefix}.mlp.up_proj.weight", (FFN, HIDDEN)),
            (f"{prefix}.mlp.down_proj.weight", (HIDDEN, FFN)),
            (f"{prefix}.input_layernorm.weight", (HIDDEN,)),
            (f"{prefix}.post_attention_layernorm.weight", (HIDDEN,)),
        ]
        for _, shape in block:
            n = 1
            for s in shape:
                n *= s
            total += n * itemsize
        tensors += block
        layer += 1
    tensors += [
        ("language_model.model.norm.weight", (HIDDEN,)),
        ("action_head.fc1.weight", (256, HIDDEN)),
    ]
    return tensors


def make_exports(root: Path, size_gb: float, dtype_name: str) -> None:
    """θ_pre random; θ_aux and θ_sft = θ_pre + small independent noise, as HF-style sharded exports."""
    import torch
    from safetensors.torch import save_file

    dtype = getattr(torch, dtype_name)
    tensors = layout(int(size_gb * 1e9), dtype.itemsize)
    for model_index, name in enumerate(NAMES):
        folder = root / name
        folder.mkdir()
        shards: list[list[str]] = [[]]
        size = 0
        for key, shape in tensors:
            nbytes = dtype.itemsize
            for s in shape:
                nbytes *= s
            if shards[-1] and size + nbytes > SHARD_BYTES:
                shards.append([])
                size = 0
            shards[-1].append(key)
            size += nbytes
        shapes = dict(tensors)
        weight_map = {}
        for i, keys in enumerate(shards):
            file = f"model-{i + 1:05d}-of-{len(shards):05d}.safetensors"
            data = {}
            for k_index, key in enumerate(keys):
                seed = hash((i, k_index)) % (2**31)
                g = torch.Generator().manual_seed(seed)
                value = 0.02 * torch.randn(shapes[key], generator=g)
                if model_index:
                    g.manual_seed(seed + model_index)
                    value += 1e-3 * torch.randn(shapes[key], generator=g)
                data[key] = value.to(dtype)
            save_file(data, str(folder / file), metadata={"format": "pt"})
            weight_map.update(dict.fromkeys(keys, file))
            del data
        total = sum(os.path.getsize(folder / f) for f in set(weight_map.values()))
        index = {"metadata": {"total_size": total}, "weight_map": weight_map}
        (folder / "model.safetensors.index.json").write_text(json.dumps(index))
        config = {
            "format": "capvector-export",
            "family": "bench",
            "capability_parameters": ["language_model.*"],
        }
        (folder / "config.json").write_text(json.dumps(config))
        (folder / "dataset_statistics.json").write_text("{}")


def run_stage(stage: str, root: Path, out: Path) -> float:
    """Run one stage in this process, writing ``out``; returns its wall time (imports excluded)."""
    if stage == "import":
        import torch  # noqa: F401

        return 0.0
    if stage == "baseline":
        import torch
        from safetensors.torch import load_file, save_file

        start = time.perf_counter()
        out.mkdir()
        index = json.loads((root / "aux" / "model.safetensors.index.json").read_text())[
            "weight_map"
        ]
        checksum = torch.zeros((), dtype=torch.float64)
        for file in sorted(set(index.values())):
            aux, sft = load_file(str(root / "aux" / file)), load_file(str(root / "sft" / file))
            # load_file maps the file lazily; a reduction makes every byte really be read.
            for tensor in (*aux.values(), *sft.values()):
                checksum += float(tensor.sum())
            save_file(aux, str(out / file), metadata={"format": "pt"})
            del aux, sft
            fd = os.open(out / file, os.O_RDONLY)
            os.fsync(fd)
            os.close(fd)
        return time.perf_counter() - start
    if stage == "extract":
        from capvector.vectors import extract

        start = time.perf_counter()
        extract(root / "aux", root / "sft", out)
        return time.perf_counter() - start
    if stage == "merge":
        from capvector.vectors import merge

        start = time.perf_counter()
        merge(root / "pre", [(root / "vector", 1.0)], out)
        return time.perf_counter() - start
    if stage == "read vector":
        start = time.perf_counter()
        buffer = memoryview(bytearray(8 * 1024**2))  # the fingerprint's piece size
        for path in sorted((root / "vector").glob("*.safetensors")):
            with open(path, "rb", buffering=0) as f:
                while f.readinto(buffer):
                    pass
        return time.perf_counter() - start
    if stage == "fingerprint":
        from capvector.vectors import VectorFolder

        start = time.perf_counter()
        VectorFolder(root / "vector").fingerprint()
        return time.perf_counter() - start
    raise ValueError(stage)


def peak_rss_kib() -> int:
    """This process's peak resident set (VmHWM). Read in the child itself: the rusage of a child
    forked from a large parent reports the parent's pre-exec size as the child's peak."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    raise RuntimeError("no VmHWM in /proc/self/status")


def measure(stage: str, root: Path, out: Path) -> tuple[float, float]:
    """(seconds, peak RSS in MiB) of ``stage`` run in a fresh Python process."""
    os.sync()  # start every stage with no dirty pages of the previous one still being written back
    cmd = [sys.executable, __file__, "--stage", stage, "--workdir", str(root), "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"stage {stage} failed:\n{done.stdout}\n{done.stderr}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return result["seconds"], result["peak_rss_kib"] / 1024


def spot_check(root: Path, merged: Path) -> None:
    """θ_merged == θ_pre + (θ_aux − θ_sft) on a few tensors (rows of the big ones), bit for bit:
    c is computed in float32 and stored in the models' dtype, the sum likewise."""
    import torch
    from safetensors import safe_open

    index = json.loads((root / "pre" / "model.safetensors.index.json").read_text())["weight_map"]
    keys = [
        k
        for k in index
        if k.endswith(("down_proj.weight", "embed_tokens.weight", "model.norm.weight"))
    ]
    for key in keys[:3]:
        rows = slice(0, 64)
        values = {}
        for name in ("pre", "aux", "sft", "merged"):
            folder = merged if name == "merged" else root / name
            with safe_open(str(folder / index[key]), "pt") as f:
                values[name] = f.get_slice(key)[rows]
        dtype = values["pre"].dtype
        vector = (values["aux"].float() - values["sft"].float()).to(dtype)
        expected = (values["pre"].float() + vector.float()).to(dtype)
        if not torch.equal(values["merged"], expected):
            raise AssertionError(f"merged `{key}` differs from pre + (aux - sft)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size-gb", type=float, default=2.0, help="size of each input model")
    parser.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
    parser.add_argument(
        "--workdir", default="/work/tmp" if Path("/work/tmp").is_dir() else tempfile.gettempdir()
    )
    parser.add_argument(
        "--repeats", type=int, default=3, help="runs per stage; the median is reported"
    )
    parser.add_argument("--keep", action="store_true", help="keep the generated folders")
    parser.add_argument("--stage", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.stage:
        seconds = run_stage(args.stage, Path(args.workdir), Path(args.out))
        print(json.dumps({"seconds": seconds, "peak_rss_kib": peak_rss_kib()}))
        return

    need = 6.5 * args.size_gb * 1e9  # three inputs, baseline, vector, merged
    free = shutil.disk_usage(args.workdir).free
    if free < need:
        sys.exit(f"{args.workdir} has {free / 1e9:.1f} GB free; this run needs {need / 1e9:.1f} GB")
    root = Path(tempfile.mkdtemp(prefix="bench_vectors-", dir=args.workdir))
    try:
        start = time.perf_counter()
        make_exports(root, args.size_gb, args.dtype)
        model_bytes = sum(f.stat().st_size for f in (root / "aux").glob("*.safetensors"))
        print(
            f"built 3 exports of {model_bytes / 1e9:.2f} GB ({args.dtype}) in {time.perf_counter() - start:.0f} s"
        )
        runs: dict[str, list[tuple[float, float]]] = {
            "import": [measure("import", root, root / "none")]
        }
        # Stages alternate, so drifting disk/writeback conditions hit all of them alike.
        for i in range(args.repeats):
            for stage in ("baseline", "extract", "merge", "read vector", "fingerprint"):
                out = root / ("vector" if (stage, i) == ("extract", 0) else f"{stage}-{i}")
                runs.setdefault(stage, []).append(measure(stage, root, out))
                if stage == "merge" and i == 0:
                    spot_check(root, out)
                if out.name != "vector":
                    shutil.rmtree(out, ignore_errors=True)  # the reading stages write nothing
        vector_bytes = sum(f.stat().st_size for f in (root / "vector").glob("*.safetensors"))
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)

    results = {
        stage: (statistics.median(t for t, _ in r), max(m for _, m in r))
        for stage, r in runs.items()
    }
    baseline = results["baseline"][0]
    print(
        f"\nInputs: 2 × {model_bytes / 1e9:.2f} GB sharded exports ({args.dtype}), vector "
        f"{vector_bytes / 1e9:.2f} GB, {os.cpu_count()} CPUs; median of {args.repeats} runs, "
        "peak RSS = max over runs.\n"
    )
    print(
        "| stage | wall time (s) | × baseline | peak RSS (MiB) | target (≤ 2× baseline, ≤ 1 GiB) |"
    )
    print("|---|---|---|---|---|")
    for stage, (seconds, rss) in results.items():
        ratio = "–" if stage in ("import", "baseline") else f"{seconds / baseline:.2f}"
        ok = ""
        if stage in ("extract", "merge"):
            ok = "met" if rss <= 1024 and seconds <= 2 * baseline else "MISSED"
        label = {"import": "python + import torch (floor)"}.get(stage, stage)
        shown = "–" if stage == "import" else f"{seconds:.1f}"
        print(f"| {label} | {shown} | {ratio} | {rss:.0f} | {ok} |")
    fingerprint, read = results["fingerprint"][0], results["read vector"][0]
    print(
        f"\nfingerprint of the {vector_bytes / 1e9:.2f} GB vector: {fingerprint:.2f} s = "
        f"{fingerprint / read:.2f}× one plain read of its files ({read:.2f} s, page cache)"
    )
    every = {
        stage: ", ".join(f"{t:.2f}" for t, _ in r) for stage, r in runs.items() if stage != "import"
    }
    print("\nall runs (s): " + "; ".join(f"{k} {v}" for k, v in every.items()))


if __name__ == "__main__":
    main()
