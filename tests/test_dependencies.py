"""Every package the code imports is declared in pyproject.toml, and in the right place: what the
training path imports at module level is a core dependency, an extra's package is imported lazily
or behind the extra's boundary (``capvector.envs`` for the simulator)."""

from __future__ import annotations

import ast
import re
import sys
from collections.abc import Iterator
from functools import cache
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib", reason="reads pyproject.toml with Python 3.11's tomllib")

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "capvector"

EXTRA_HOMES = {"sim": "capvector.envs", "libero": "capvector.envs", "metaworld": "capvector.envs"}
"""Packages where an extra's modules may be imported at module level: they need the extra (and
raise ``missing_extra`` when it is absent); everywhere else an extra is imported inside functions."""


def _name(requirement: str) -> str:
    """``jsonargparse[signatures]>=4.35`` -> ``jsonargparse`` (PEP 503 normalised)."""
    return re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9._-]+", requirement).group()).lower()


def _no_deps() -> dict[str, list[str]]:
    """``[tool.capvector.no-deps]``: requirements installed without their dependencies, by the
    extra they complete (Meta-World, whose MuJoCo pin we override)."""
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return pyproject.get("tool", {}).get("capvector", {}).get("no-deps", {})


def _declared() -> tuple[set[str], dict[str, set[str]]]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {_name(r) for r in project["dependencies"]}
    extras = {
        extra: {_name(r) for r in requirements}
        for extra, requirements in project["optional-dependencies"].items()
    }
    for extra, requirements in _no_deps().items():
        extras[extra] |= {_name(r) for r in requirements}
    return core, extras


def test_the_makefile_installs_the_no_deps_requirements() -> None:
    """``make`` installs each ``[tool.capvector.no-deps]`` requirement after its extra, without
    dependencies: otherwise the extra is installed and its package is not."""
    makefile = (ROOT / "Makefile").read_text()
    extras_installed = re.search(r'-e "\.\[([^\]]*)\]"', makefile).group(1).split(",")
    for extra, requirements in _no_deps().items():
        assert extra in extras_installed, f"the Makefile does not install the {extra} extra"
        for requirement in requirements:
            assert f'--no-deps "{requirement}"' in makefile, f"the Makefile lacks {requirement}"


@cache
def _installed() -> dict[str, list[str]]:
    return packages_distributions()  # reads every installed package's metadata: once


@cache
def _distribution(top_level: str) -> str:
    """The installed distribution that provides an import name (``yaml`` -> ``pyyaml``)."""
    provided = _installed().get(top_level)
    return _name(provided[0] if provided else top_level)


def _imports(path: Path) -> Iterator[tuple[str, bool]]:
    """(top-level import name, imported at module level) for each third-party import."""
    tree = ast.parse(path.read_text(), filename=str(path))
    nested = {
        id(node)
        for func in ast.walk(tree)
        if isinstance(func, ast.FunctionDef | ast.AsyncFunctionDef)
        for node in ast.walk(func)
    }
    type_checking = {
        id(node)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and ast.unparse(block.test).endswith("TYPE_CHECKING")
        for node in ast.walk(block)
    }
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        if id(node) in type_checking:
            continue
        for name in names:
            top = name.split(".")[0]
            if top not in sys.stdlib_module_names and top != "capvector":
                yield top, id(node) not in nested


def _module(path: Path) -> str:
    return ".".join(path.relative_to(SRC.parent).with_suffix("").parts).removesuffix(".__init__")


def test_every_import_of_the_package_is_declared_where_it_belongs() -> None:
    core, extras = _declared()
    wrong = []
    for path in sorted(SRC.rglob("*.py")):
        module = _module(path)
        for top, module_level in _imports(path):
            dist = _distribution(top)
            if dist in core:
                continue
            owners = sorted(extra for extra, names in extras.items() if dist in names)
            if not owners:
                wrong.append(
                    f"{module}: imports {top} ({dist}), which pyproject.toml declares nowhere"
                )
            elif module_level and not any(
                module.startswith(EXTRA_HOMES.get(extra, "\0")) for extra in owners
            ):
                wrong.append(
                    f"{module}: imports {top} of the {'/'.join(owners)} extra at module level; "
                    "import it inside the function that needs it (see errors.missing_extra)"
                )
    assert not wrong, "\n".join(wrong)


def test_every_import_of_the_tests_and_benchmarks_is_declared() -> None:
    core, extras = _declared()
    declared = core.union(*extras.values())
    # The repository's own scripts (tests/tools import a tool script from its folder) count as local.
    local = {
        p.stem for folder in ("tests", "benchmarks", "tools") for p in (ROOT / folder).rglob("*.py")
    }
    wrong = sorted(
        f"{path.relative_to(ROOT)}: imports {top} ({_distribution(top)})"
        for folder in ("tests", "benchmarks")
        for path in (ROOT / folder).rglob("*.py")
        for top, _ in _imports(path)
        if top not in local and _distribution(top) not in declared
    )
    assert not wrong, "declared in no dependency list of pyproject.toml:\n" + "\n".join(wrong)


def test_rollout_validation_without_the_simulator_stops_before_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    from capvector.cli import main
    from conftest import write_demo_file

    data = write_demo_file(tmp_path / "demos.hdf5")
    for simulator in ("mujoco", "robosuite"):  # what an environment without the sim extra sees
        monkeypatch.setitem(sys.modules, simulator, None)
    out = tmp_path / "runs"
    code = main([
        "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=1", f"--trainer.default_root_dir={out}",
        "--model.backbone=openvla-oft-tiny", f"--data.train_files=[{data}]",
        "--data.eval_tasks=[{task: Lift, episodes: 1}]",
    ])  # fmt: skip
    assert code == 2
    assert capfd.readouterr().err.splitlines()[-1] == (
        "capvector fit: error: rollout validation (data.eval_tasks) needs the sim extra: "
        "pip install 'capvector[sim]' (No module named 'mujoco')"
    )
    assert not out.exists()
