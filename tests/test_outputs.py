"""No command loses data: an output is never an input, never inside one and never holds one; an
existing output is replaced only with --overwrite; of two writers of one output one wins and the
other stops at once; a writer that is killed leaves nothing the next run does not remove.

Each case: exit code 2, one line naming the problem, no output left, every input byte-identical.
Writers that run at once or are killed are real ``capvector merge`` processes.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path

# Lightning binds its log handler to the stderr of the moment it is imported: import it now, not
# inside a test whose captured stream closes after it.
import lightning.pytorch  # noqa: F401
import pytest
import torch

from capvector.backbones import build_backbone
from capvector.cli import main
from capvector.errors import CapVectorError
from capvector.io.outputs import (
    MARKER,
    atomic_directory,
    atomic_write_bytes,
    remove_writer_leftovers,
)
from capvector.vectors import extract
from conftest import write_demo_file
from test_cli_errors import fit_args, tree_digest

PRESET = "openvla-oft-tiny"


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``P`` holding a base (= θ_sft), θ_aux (θ_sft with one tensor moved) and their vector."""
    root = tmp_path_factory.mktemp("project") / "P"
    model = build_backbone(PRESET)
    model.save_pretrained(root / "base")
    model.save_pretrained(root / "sft")
    with torch.no_grad():
        dict(model.named_parameters())[model.capability_parameter_names()[0]].add_(0.01)
    model.save_pretrained(root / "aux")
    extract(aux=root / "aux", sft=root / "sft", out=root / "vec")
    return root


def merge_args(project: Path, out: Path | str, *extra: str) -> list[str]:
    return ["merge", "--base", str(project / "base"), "--vector", f"{project / 'vec'}:1",
            "--out", str(out), *extra]  # fmt: skip


def leftovers(folder: Path, name: str) -> list[str]:
    """Temporaries and lock files of the output ``name`` in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(f".{name}."))


def run_refused(args: list[str], message: str, capfd: pytest.CaptureFixture[str]) -> None:
    code = main(args)
    errors = [line for line in capfd.readouterr().err.splitlines() if "error" in line]
    assert code == 2
    assert len(errors) == 1 and errors[0].startswith("capvector "), errors
    assert re.search(message, errors[0]), errors[0]


@pytest.mark.parametrize(
    "case",
    [
        "merge --out the folder holding base and vector, --overwrite",
        "extract --out the folder holding aux and sft, --overwrite",
        "merge --out the base itself, --overwrite",
        "merge --out inside the base",
        "merge --out inside the vector",
        "extract --out inside aux",
        "compose --out the folder holding the vector, --overwrite",
        "inspect --plot inside the vector",
    ],
)
def test_an_output_never_touches_an_input(
    case: str, project: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    p = project
    extract_args = ["extract", "--aux", str(p / "aux"), "--sft", str(p / "sft"), "--out"]
    args, new_output, message = {
        "merge --out the folder holding base and vector, --overwrite": (
            merge_args(p, p, "--overwrite"), None, f"--out {p} holds the input {p / 'base'}"),
        "extract --out the folder holding aux and sft, --overwrite": (
            [*extract_args, str(p), "--overwrite"], None, f"--out {p} holds the input {p / 'aux'}"),
        "merge --out the base itself, --overwrite": (
            merge_args(p, p / "base", "--overwrite"), None, f"--out {p / 'base'} is an input"),
        "merge --out inside the base": (
            merge_args(p, p / "base" / "merged"), p / "base" / "merged",
            f"--out {p / 'base' / 'merged'} lies inside the input {p / 'base'}"),
        "merge --out inside the vector": (
            merge_args(p, p / "vec" / "sub" / "m"), p / "vec" / "sub",
            f"--out {p / 'vec' / 'sub' / 'm'} lies inside the input {p / 'vec'}"),
        "extract --out inside aux": (
            [*extract_args, str(p / "aux" / "v")], p / "aux" / "v",
            f"--out {p / 'aux' / 'v'} lies inside the input {p / 'aux'}"),
        "compose --out the folder holding the vector, --overwrite": (
            ["compose", "--vectors", str(p / "vec"), "--out", str(p), "--overwrite"], None,
            f"--out {p} holds the input {p / 'vec'}"),
        "inspect --plot inside the vector": (
            ["inspect", str(p / "vec"), "--plot", str(p / "vec" / "norms.png")],
            p / "vec" / "norms.png", f"--plot {p / 'vec' / 'norms.png'} lies inside the input {p / 'vec'}"),
    }[case]  # fmt: skip
    before = tree_digest(p)
    what = message.split()[0]
    run_refused(args, re.escape(f"{message}; an output must be outside every input: choose another {what}"), capfd)  # fmt: skip
    assert tree_digest(p) == before  # nothing removed, nothing added
    assert new_output is None or not new_output.exists()
    assert not [f for f in p.rglob(".*") if f.name != MARKER], "a temporary or lock file was left"


def test_an_out_that_is_a_symbolic_link_loop_is_one_line(
    project: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    before = tree_digest(project)
    for out in (loop, loop / "merged"):
        run_refused(merge_args(project, out), rf"--out {out} goes through a symbolic link that loops", capfd)  # fmt: skip
    assert sorted(tmp_path.iterdir()) == [loop] and tree_digest(project) == before


def test_without_overwrite_an_output_that_appears_meanwhile_is_never_moved_aside(
    tmp_path: Path,
) -> None:
    target = tmp_path / "out"
    appeared = re.escape(
        f"{target} appeared while this command was writing it; it was left as it is"
    )
    with pytest.raises(CapVectorError, match=appeared), atomic_directory(target) as tmp:
        (tmp / "ours.txt").write_text("ours")
        target.mkdir()  # another program's result, made after the check
        (target / "theirs.txt").write_text("theirs")
    assert (target / "theirs.txt").read_text() == "theirs" and len(list(target.iterdir())) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # With overwrite the new result replaces a result of capvector's whole (another program's
    # folder, without the marker, is refused), and nothing else is left beside it.
    (target / MARKER).touch()
    with atomic_directory(target, overwrite=True) as tmp:
        (tmp / "ours.txt").write_text("ours")
    assert sorted(p.name for p in target.iterdir()) == [MARKER, "ours.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


# A real `capvector merge` that stops once its temporary output holds every tensor and waits for
# the file named by argv[1]: what the tests below do to it happens mid-write, every time. The
# pause only delays `finish`; the merge itself is the real one.
PAUSED_MERGE = textwrap.dedent("""
    import os, sys, time
    from capvector.cli import main
    from capvector.io.weights import SafetensorsWriter

    finish = SafetensorsWriter.finish

    def paused(self):
        print("writing", flush=True)
        while not os.path.exists(sys.argv[1]):
            time.sleep(0.05)
        finish(self)

    SafetensorsWriter.finish = paused
    sys.exit(main(sys.argv[2:]))
""")


def start_paused_merge(project: Path, out: Path, go: Path) -> subprocess.Popen[str]:
    process = subprocess.Popen(
        [sys.executable, "-c", PAUSED_MERGE, str(go), *merge_args(project, out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert process.stdout is not None and process.stdout.readline() == "writing\n"
    return process


def capvector(args: list[str]) -> subprocess.Popen[str]:
    command = [sys.executable, "-c", "import sys; from capvector.cli import main; sys.exit(main())"]
    return subprocess.Popen([*command, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip


def test_a_second_writer_of_one_output_stops_at_once(project: Path, tmp_path: Path) -> None:
    out, go = tmp_path / "merged", tmp_path / "go"
    before = tree_digest(project)
    first = start_paused_merge(project, out, go)
    # One second writer: a third would meet the same lock (and
    # test_writers_racing_for_one_output_exactly_one_wins runs 3 at once).
    other = capvector(merge_args(project, out))
    _, err = other.communicate(timeout=300)
    assert other.returncode == 2, err
    assert re.fullmatch(
        rf"capvector merge: error: another capvector process is writing {out} "
        rf"\(pid {first.pid}\); wait for it to finish or choose another --out\n", err
    ), err  # fmt: skip
    go.touch()
    _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    assert main(merge_args(project, tmp_path / "alone")) == 0
    assert tree_digest(out)["model.safetensors"] == tree_digest(tmp_path / "alone")["model.safetensors"]  # fmt: skip
    assert leftovers(tmp_path, "merged") == [] and tree_digest(project) == before


def test_writers_racing_for_one_output_exactly_one_wins(project: Path, tmp_path: Path) -> None:
    out = tmp_path / "merged"
    racers = [capvector(merge_args(project, out)) for _ in range(3)]
    results = [(r.wait(timeout=300), r.communicate()[1]) for r in racers]
    assert sorted(code for code, _ in results) == [0, 2, 2], results
    for code, err in results:
        if code == 2:  # it met the winner writing, or its finished result
            assert re.fullmatch(
                rf"capvector merge: error: (another capvector process is writing {out} .*|"
                rf"{out} exists; choose another --out or pass --overwrite)\n", err
            ), err  # fmt: skip
    assert leftovers(tmp_path, "merged") == []
    assert (out / "model.safetensors").is_file()


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_a_killed_writer_leaves_nothing_behind_after_the_next_run(
    how: signal.Signals, project: Path, tmp_path: Path
) -> None:
    out, go = tmp_path / "merged", tmp_path / "go"
    before = tree_digest(project)
    writer = start_paused_merge(project, out, go)
    temporaries = [n for n in leftovers(tmp_path, "merged") if ".tmp-" in n]
    assert len(temporaries) == 1 and temporaries[0].startswith(f".merged.tmp-{writer.pid}-")
    writer.send_signal(how)
    writer.communicate(timeout=60)
    if how == signal.SIGTERM:  # the CLI turns it into an exit that cleans up
        assert writer.returncode == 128 + how
        assert leftovers(tmp_path, "merged") == [] and not out.exists()
    else:  # nothing runs on SIGKILL: its temporary folder stays, until the next writer
        assert writer.returncode == -how
        assert temporaries[0] in leftovers(tmp_path, "merged") and not out.exists()
    assert main(merge_args(project, out)) == 0
    assert leftovers(tmp_path, "merged") == [] and tree_digest(project) == before


# Issue 62, items 4 and 5: a full disk is one line, and --overwrite replaces only our outputs.


@pytest.fixture
def full_disk(tmp_path: Path) -> Iterator[Path]:
    """A 1 MB tmpfs, too small for any output of the tiny presets (mounting needs root)."""
    folder = tmp_path / "full"
    folder.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(folder)],
                             capture_output=True, text=True)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {mounted.stderr.strip() or 'not root'}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=True)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Demos and a one-step fit's checkpoint (``runs/**/*.ckpt``), for `fit` and `export`."""
    root = tmp_path_factory.mktemp("fit")
    write_demo_file(root / "demos.hdf5")
    args = [*fit_args(root, root / "runs"), "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint"]  # fmt: skip
    assert main(args) == 0
    return root


FULL_DISK_WRITERS: dict[str, Callable[[Path, Path, Path], list[str]]] = {
    "merge": lambda p, f, out: merge_args(p, out / "merged"),
    "extract": lambda p, f, out: ["extract", "--aux", str(p / "aux"), "--sft", str(p / "sft"), "--out", str(out / "vec")],
    "compose": lambda p, f, out: ["compose", "--vectors", str(p / "vec"), str(p / "vec"), "--out", str(out / "sum")],
    "export": lambda p, f, out: ["export", "--ckpt", str(next(f.rglob("*.ckpt"))), "--out", str(out / "export")],
    "demos": lambda p, f, out: ["demos", "--task", "Lift", "--episodes", "1", "--no-progress", "--out", str(out / "d.hdf5")],
    "fit": lambda p, f, out: fit_args(f, out / "runs"),
}  # fmt: skip


@pytest.mark.parametrize("writer", sorted(FULL_DISK_WRITERS))
def test_a_full_disk_is_one_line_naming_the_path(
    writer: str,
    project: Path,
    fitted: Path,
    full_disk: Path,
    capfd: pytest.CaptureFixture[str],
) -> None:
    """`demos` crashed in libhdf5 (exit 139) and left a 2 MB temporary and its lock; `export` printed
    a traceback; merge, extract and compose only `[Errno 28] No space left on device`. A fit
    refuses before step 0 (a partial run folder was left)."""
    before = tree_digest(project)
    capfd.readouterr()
    code = main(FULL_DISK_WRITERS[writer](project, fitted, full_disk))
    err = capfd.readouterr().err
    errors = [line for line in err.splitlines() if "error" in line.lower()]
    assert code == 2, err
    assert len(errors) == 1 and "Traceback" not in err, err
    assert re.fullmatch(
        rf"capvector {writer}: error: cannot write .*{full_disk}\S*: (its disk filled up while "
        r"writing it \(.* free once the partial output was removed\)|it needs about .* and its disk has .* free); free space "
        r"there or choose another \S+", errors[0]), errors[0]  # fmt: skip
    assert list(full_disk.iterdir()) == [], "a temporary, lock or partial output was left"
    assert tree_digest(project) == before


def test_atomic_writers_turn_a_full_disk_into_one_line(full_disk: Path) -> None:
    """Files (reports, results) and folders alike, whichever library met the full disk (Python's
    ENOSPC, or safetensors' Rust error without an errno)."""
    from safetensors.torch import save_file

    too_big = b"x" * 2_000_000
    with pytest.raises(
        CapVectorError, match=rf"cannot write output {full_disk / 'r.json'}: its disk filled up"
    ):
        atomic_write_bytes(full_disk / "r.json", too_big)
    full = pytest.raises(CapVectorError, match=r"its disk filled up while writing it")
    with full, atomic_directory(full_disk / "weights") as tmp:
        save_file({"w": torch.zeros(500_000)}, str(tmp / "w.safetensors"))
    assert list(full_disk.iterdir()) == []


def test_overwrite_replaces_only_what_capvector_wrote(
    project: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """`merge --out "$PWD" --overwrite` deleted the unrelated files of the working folder;
    `--out some_demos.hdf5 --overwrite` replaced a file with a folder; `--out .` was a 24-line
    `OSError: [Errno 16]`."""
    work = tmp_path / "work" / "here"
    work.mkdir(parents=True)
    (work / "notes.txt").write_text("mine")
    (work / "some_demos.hdf5").write_bytes(b"demos")
    (work / "theirs").mkdir()
    (work / "theirs" / "x.txt").write_text("theirs")
    monkeypatch.chdir(work)
    before = tree_digest(tmp_path)
    working = "is the working folder: an output folder replaces what is at its path, so it must be a new folder"  # fmt: skip
    for out, message in [
        (".", rf"--out \. {working}; choose one, e.g\. --out out"),
        (str(work), rf"--out {work} {working}"),
        ("..", r"--out \.\. holds the working folder"),
        (str(tmp_path), rf"--out {tmp_path} holds the working folder"),
        ("some_demos.hdf5", r"--out some_demos\.hdf5 is a file, and this output is a folder: --overwrite replaces only a folder capvector wrote"),
        ("theirs", r"--out theirs is a folder capvector did not write \(it has no \.capvector-output file\), so --overwrite will not replace it"),
    ]:  # fmt: skip
        for extra in ([], ["--overwrite"]) if out in (".", "..") else (["--overwrite"],):
            run_refused(merge_args(project, out, *extra), message, capfd)
    assert tree_digest(tmp_path) == before
    assert sorted(p.name for p in work.iterdir()) == ["notes.txt", "some_demos.hdf5", "theirs"]
    # An empty folder, and an output capvector wrote (it has the marker), are replaced.
    (work / "empty").mkdir()
    for out in ("empty", "merged", "merged"):
        assert main(merge_args(project, out, "--overwrite")) == 0
        assert (work / out / MARKER).is_file() and (work / out / "model.safetensors").is_file()
    assert sorted(p.name for p in work.iterdir()) == ["empty", "merged", "notes.txt", "some_demos.hdf5", "theirs"]  # fmt: skip


def test_write_safetensors_is_what_safetensors_reads(tmp_path: Path) -> None:
    """The streamed export writer against safetensors' own reader: every dtype an export holds,
    a 0-d and an empty tensor, a non-contiguous view."""
    from safetensors.torch import load_file

    from capvector.io.weights import write_safetensors

    tensors = {
        "w": torch.randn(5, 3, dtype=torch.bfloat16),
        "b": torch.randn(7),
        "t": torch.randn(4, 6).T,
        "i": torch.arange(4),
        "m": torch.tensor([True, False]),
        "s": torch.tensor(2.5, dtype=torch.float16),
        "e": torch.zeros(0, 3),
    }
    write_safetensors(tmp_path / "model.safetensors", tensors)
    read = load_file(tmp_path / "model.safetensors")
    assert read.keys() == tensors.keys()
    for key, tensor in tensors.items():
        assert read[key].dtype == tensor.dtype and torch.equal(read[key], tensor), key


def test_a_writers_leftovers_go_and_another_writers_stay(tmp_path: Path) -> None:
    """What a process ended on the spot leaves (its temporaries, a file or a folder, and its lock
    files) is removed by its pid; another live writer's are not touched."""
    mine, other = 4242, os.getpid()
    for pid in (mine, other):
        (tmp_path / f".a.hdf5.tmp-{pid}-x1y2.hdf5").write_bytes(b"half")
        (tmp_path / f".run.tmp-{pid}-abc").mkdir()
        (tmp_path / f".{pid}.lock").write_text(str(pid))
    (tmp_path / "a.hdf5").write_bytes(b"a finished file")
    remove_writer_leftovers(tmp_path, mine)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["a.hdf5", f".a.hdf5.tmp-{other}-x1y2.hdf5", f".run.tmp-{other}-abc", f".{other}.lock"]
    )
