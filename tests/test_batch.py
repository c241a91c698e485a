"""The batch has one declaration (``capvector.data.batch``): the datamodule's batches carry exactly
its keys, and no code in ``src/`` reads a key it does not declare."""

from __future__ import annotations

import ast
from pathlib import Path

import lightning as L
import torch

import capvector
from capvector.data import keys
from capvector.data.batch import Batch, Sample
from capvector.data.datamodule import RobotDataModule
from conftest import cpu_trainer

SRC = Path(capvector.__file__).parent
BATCH_NAMES = ("batch", "sample")
"""The variables that hold a ``Batch`` or a ``Sample`` everywhere in ``src/``."""


def declared(typed_dict: type) -> set[str]:
    return set(typed_dict.__required_keys__ | typed_dict.__optional_keys__)


class BatchRecorder(L.LightningModule):
    def __init__(self) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(()))
        self.batches: list[Batch] = []

    def training_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        self.batches.append(batch)
        return self.w**2

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.SGD(self.parameters(), lr=0.1)


def test_the_datamodule_batch_has_exactly_the_declared_keys(
    demo_file: Path, tmp_path: Path
) -> None:
    dm = RobotDataModule(
        train_files=[str(demo_file)], batch_size=4, load_depth=True, load_annotations=True
    )
    dm.setup("fit")
    sample = dm.train_dataset[0]
    assert set(sample) == declared(Sample)
    module = BatchRecorder()
    cpu_trainer(1, tmp_path).fit(module, dm)
    (batch,) = module.batches
    assert set(batch) == declared(Batch)
    # The shapes and dtypes the declaration documents (2 cameras, 64 px, 8-d proprio, 8 x 7 chunk).
    assert batch["images"].shape == (4, 2, 3, 64, 64) and batch["images"].dtype == torch.float32
    assert batch["proprio"].shape == (4, 8) and batch["actions"].shape == (4, 8, 7)
    assert batch["depth"].shape == (4, 2, 64, 64) and batch["intrinsics"].shape == (4, 2, 3, 3)
    assert batch["index"].dtype == batch["noise_seed"].dtype == torch.int64
    assert all(isinstance(text, str) for text in batch["instruction"] + batch["annotation"])
    # What acting passes (``VLAPolicy``) is the required part; a dataset's sample adds the rest.
    assert declared(Sample) == declared(Batch) - {"noise_seed"}
    assert Batch.__required_keys__ == {"images", "proprio", "instruction"}


def typed_dicts_extending_batch() -> set[str]:
    """Keys of the TypedDicts in ``src/`` that extend ``Batch`` with a family's own input."""
    found = set()
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                isinstance(b, ast.Name) and b.id == "Batch" for b in node.bases
            ):
                found |= {
                    s.target.id
                    for s in node.body
                    if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)
                }
    return found


def undeclared_reads(source: str, where: str, known: set[str]) -> list[str]:
    """``batch["x"]``, ``batch.get("x")`` and ``"x" in batch`` with an ``x`` not in ``known``, and
    keys that are not literals (``batch[KEY]``), which a type checker cannot verify."""
    wrong = []

    def held(node: ast.AST) -> bool:
        return isinstance(node, ast.Name) and node.id in BATCH_NAMES

    def check(key: ast.AST, line: int) -> None:
        if isinstance(key, ast.Constant) and not isinstance(key.value, str):
            return  # a list index (an episode batch)
        if not (isinstance(key, ast.Constant) and key.value in known):
            wrong.append(f"{where}:{line}: {ast.unparse(key)}")

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Subscript) and held(node.value):
            check(node.slice, node.lineno)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "get"
            and held(node.func.value)
            and node.args
        ):
            check(node.args[0], node.lineno)
        elif (
            isinstance(node, ast.Compare)
            and any(held(c) for c in node.comparators)
            and any(isinstance(op, ast.In | ast.NotIn) for op in node.ops)
        ):
            check(node.left, node.lineno)
    return wrong


def test_src_reads_only_declared_batch_keys_as_literals() -> None:
    known = declared(Batch) | typed_dicts_extending_batch()
    assert known - declared(Batch) == {"image_mask"}  # Pi05Batch: Pi0.5's camera mask
    wrong = [
        line
        for path in sorted(SRC.rglob("*.py"))
        for line in undeclared_reads(path.read_text(), str(path.relative_to(SRC)), known)
    ]
    assert not wrong, "declare these keys in capvector/data/batch.py or fix them:\n" + "\n".join(
        wrong
    )


def test_the_scan_finds_a_misspelt_or_indirect_key() -> None:
    source = 'batch["instrucion"]\nbatch.get(keys.PROPRIO)\n"deph" in batch\nbatch["images"]\n'
    assert undeclared_reads(source, "x.py", declared(Batch)) == [
        "x.py:1: 'instrucion'",
        "x.py:2: keys.PROPRIO",
        "x.py:3: 'deph'",
    ]


def test_src_uses_the_literal_keys_and_the_constants_name_the_same_keys() -> None:
    importers = [
        str(path.relative_to(SRC))
        for path in SRC.rglob("*.py")
        if "data import keys" in path.read_text() or "data.keys" in path.read_text()
    ]
    assert not importers, f"index the batch with Batch's literal keys instead: {importers}"
    constants = {v for k, v in vars(keys).items() if k.isupper()}
    assert constants == declared(Batch)
