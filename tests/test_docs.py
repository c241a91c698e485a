"""The docs are checked like code: the MkDocs site builds strictly, the README's relative links
resolve, and every code block marked runnable (the line ``<!-- runnable -->`` before its fence) in
README.md and docs/ runs. The backbone example also trains through VLAModule."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
import textwrap
import types
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from capvector.backbones import build_backbone, list_presets
from capvector.data import keys
from capvector.module import VLAModule
from conftest import restored_registry

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
RUNNABLE = "<!-- runnable -->"
FENCE = re.compile(r"^(\s*)(`{3,})\s*([\w+-]*)")
# [text](target) and ![alt](target), with an optional "title".
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


@dataclass(frozen=True)
class Block:
    """A fenced code block of a Markdown file."""

    path: Path
    line: int  # of the opening fence, 1-based
    language: str
    code: str
    runnable: bool

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def markdown_files() -> list[Path]:
    return [README, *sorted((ROOT / "docs").rglob("*.md"))]


def code_blocks(path: Path) -> list[Block]:
    lines = path.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        opening = FENCE.match(lines[i])
        if opening is None:
            i += 1
            continue
        fence = opening.group(2)
        end = next(
            (j for j in range(i + 1, len(lines)) if lines[j].strip().startswith(fence)), len(lines)
        )
        marked = i > 0 and lines[i - 1].strip() == RUNNABLE
        code = textwrap.dedent("\n".join(lines[i + 1 : end])) + "\n"
        blocks.append(Block(path, i + 1, opening.group(3), code, marked))
        i = end + 1
    return blocks


def runnable_blocks() -> list[Block]:
    return [b for path in markdown_files() for b in code_blocks(path) if b.runnable]


def run_python(block: Block, monkeypatch: pytest.MonkeyPatch) -> types.ModuleType:
    """Runs the block as the body of a fresh module (dataclasses look their module up in
    sys.modules); the caller undoes backbone registrations."""
    module = types.ModuleType("docs_example_" + re.sub(r"\W", "_", block.name))
    monkeypatch.setitem(sys.modules, module.__name__, module)
    exec(compile(block.code, block.name, "exec"), module.__dict__)
    return module


def run_bash(block: Block, folder: Path) -> None:
    """Runs the block in ``folder``, which sees the repository's assets/, configs/ and docs/ (the
    committed results), with this environment's ``capvector`` first on PATH."""
    bin_dir = Path(sys.executable).parent
    assert (bin_dir / "capvector").exists(), (
        f"no capvector beside {sys.executable}: pip install -e ."
    )
    for name in ("assets", "configs", "docs"):
        (folder / name).symlink_to(ROOT / name)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    done = subprocess.run(
        ["bash", "-e", "-o", "pipefail", "-c", block.code],
        cwd=folder, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, (
        f"{block.name} exited with {done.returncode}\n--- stdout\n{done.stdout[-3000:]}"
        f"\n--- stderr\n{done.stderr[-3000:]}"
    )


@pytest.mark.parametrize("block", runnable_blocks(), ids=lambda b: b.name)
def test_runnable_block_runs(
    block: Block, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, scoped_registry: None
) -> None:
    monkeypatch.chdir(tmp_path)  # whatever a block writes lands in a fresh folder
    if block.language == "python":
        run_python(block, monkeypatch)
    elif block.language in ("bash", "sh", "shell"):
        run_bash(block, tmp_path)
    else:
        pytest.fail(f"{block.name}: no runner for a {block.language or 'plain'} block; mark only python or bash blocks")  # fmt: skip


def test_every_marker_stands_before_a_code_block() -> None:
    stray = []
    for path in markdown_files():
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines):
            if line.strip() == RUNNABLE and (i + 1 == len(lines) or not FENCE.match(lines[i + 1])):
                stray.append(f"{path.relative_to(ROOT)}:{i + 1}")
    assert not stray, f"{RUNNABLE} must be the line right before a code fence: {stray}"


def test_the_examples_we_rely_on_are_marked_runnable() -> None:
    """An unmarked example would silently drop out of the test above."""
    marked = runnable_blocks()
    assert any(b.path == README and "capvector merge" in b.code for b in marked)
    assert any(b.language == "python" and "register_family" in b.code for b in marked)


def backbone_example() -> Block:
    return next(b for b in runnable_blocks() if "register_family" in b.code)


def test_backbone_example_builds_and_trains(
    monkeypatch: pytest.MonkeyPatch, scoped_registry: None
) -> None:
    run_python(backbone_example(), monkeypatch)
    model = build_backbone("tiny-mlp")
    batch = {
        keys.IMAGES: torch.rand(4, 2, 3, 64, 64),
        keys.PROPRIO: torch.rand(4, 8),
        keys.ACTIONS: torch.rand(4, 8, 7),
        keys.INSTRUCTION: ["lift"] * 4,
    }
    module = VLAModule(backbone="tiny-mlp")
    optimizer = torch.optim.AdamW(module.parameters(), lr=1e-2)
    first = module.compute_losses(batch)["action"].item()
    for _ in range(20):
        loss = module.compute_losses(batch)["action"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert loss.item() < first
    assert model.capability_parameter_names() == ["body.0.weight", "body.0.bias"]


def test_the_example_preset_is_registered_only_inside_its_test(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with restored_registry():
        run_python(backbone_example(), monkeypatch)
        assert "tiny-mlp" in list_presets()
    assert "tiny-mlp" not in list_presets() and "openvla-oft-tiny" in list_presets()


def test_peft_snippet_names_real_functions() -> None:
    """The peft snippet's imports and calls exist (tests/test_vectors_extract.py runs the same
    steps on real folders and compares with `capvector merge`)."""
    block = next(
        b
        for path in markdown_files()
        for b in code_blocks(path)
        if b.language == "python" and "PeftModel" in b.code
    )
    namespace: dict = {}
    exec(compile("\n".join(line for line in block.code.splitlines() if line.startswith("from")), block.name, "exec"), namespace)  # fmt: skip
    assert {"PeftModel", "from_pretrained", "VectorFolder", "apply_vector_"} <= set(namespace)
    assert hasattr(namespace["VectorFolder"], "load_outside_adapter")


def without_code(markdown: str) -> str:
    """The text outside fenced blocks and inline code, where a link is a link."""
    markdown = re.sub(r"^\s*(`{3,}).*?^\s*\1", "", markdown, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", markdown)


def heading_anchors(path: Path) -> set[str]:
    """The anchors MkDocs gives the headings of a page (Python-Markdown's toc slugs)."""
    from markdown.extensions.toc import slugify

    headings = re.findall(r"^#{1,6}\s+(.+?)\s*#*$", without_code(path.read_text()), flags=re.M)
    return {slugify(h, "-") for h in headings}


def test_readme_links_point_to_files_that_exist() -> None:
    """MkDocs checks the links inside docs/; README.md is outside it, so it is checked here."""
    broken = []
    for target in LINK.findall(without_code(README.read_text())):
        if re.match(r"[a-zA-Z][\w+.-]*:", target):
            continue  # https:, mailto:
        file, _, anchor = target.partition("#")
        path = (README.parent / file) if file else README
        if not path.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and path.suffix == ".md" and anchor not in heading_anchors(path):
            broken.append(f"{target} (no heading makes #{anchor})")
    assert not broken, f"README.md links to what does not exist: {broken}"


def test_readme_names_the_two_setup_commands() -> None:
    text = README.read_text()
    assert "make demo" in text and "make test" in text


def build_site(config: Path, site: Path) -> subprocess.CompletedProcess[str]:
    assert importlib.util.find_spec("mkdocs"), "mkdocs is missing: pip install -e '.[dev]'"
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(config)]
    return subprocess.run(
        [*command, "--site-dir", str(site)], cwd=config.parent, capture_output=True, text=True
    )


def test_docs_site_builds_strictly(tmp_path: Path) -> None:
    done = build_site(ROOT / "mkdocs.yml", tmp_path / "site")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-5000:]
    assert (tmp_path / "site" / "index.html").exists()
    assert (tmp_path / "site" / "results" / "powered" / "success_vs_steps.png").exists()


@pytest.mark.parametrize(
    "link", ["[a page](no-such-page.md)", "[an anchor](results.md#no-such-heading)"]
)
def test_docs_build_fails_on_a_broken_link(tmp_path: Path, link: str) -> None:
    """What the strict build above guards: a link MkDocs cannot resolve stops it."""
    shutil.copy(ROOT / "mkdocs.yml", tmp_path / "mkdocs.yml")
    shutil.copytree(ROOT / "docs", tmp_path / "docs")
    with (tmp_path / "docs" / "index.md").open("a") as f:
        f.write(f"\n{link}\n")
    done = build_site(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert done.returncode != 0
    assert link.split("(")[1].rstrip(")") in done.stderr
