"""Bad data is refused where it enters, before training: one line naming the file, the demo and
the key, exit code 2, no run or log folder, the data files byte for byte as they were."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from capvector.backbones import build_backbone
from capvector.cli import main
from capvector.data.statistics import check_finite_statistics, compute_statistics
from capvector.errors import CapVectorError
from conftest import CAMERAS, write_demo_file
from test_cli_errors import fit_args, tree_digest


def _set(path: Path, key: str, change: Callable[[np.ndarray], np.ndarray]) -> None:
    """Replace dataset ``key`` of the HDF5 file by ``change`` of its values (any shape, dtype)."""
    with h5py.File(path, "a") as f:
        values = change(f[key][()])
        del f[key]
        f[key] = values


def _with(values: np.ndarray, index: tuple[int, ...], value: float) -> np.ndarray:
    values = values.copy()
    values[index] = value
    return values


def _smaller_images_in_demo_1(path: Path) -> None:
    for camera in CAMERAS:  # 32x32 instead of 64x64; demo_1 has 10 steps
        _set(path, f"data/demo_1/obs/{camera}_image", lambda _: np.zeros((10, 32, 32, 3), np.uint8))


def _delete(path: Path, key: str) -> None:
    with h5py.File(path, "a") as f:
        del f[key]


def _no_demos(path: Path) -> None:
    path.unlink()
    with h5py.File(path, "w") as f:
        f.create_group("data").attrs["language_instruction"] = "lift the red cube"


# name: (how to break demos.hdf5, the error message); demos.hdf5 holds demo_0 (12 steps), demo_1 (10).
HDF5_CASES: dict[str, tuple[Callable[[Path], None], str]] = {
    "one nan in one demo's actions": (
        lambda p: _set(p, "data/demo_1/actions", lambda a: _with(a, (3, 2), np.nan)),
        r"demos\.hdf5:data/demo_1/actions has 1 non-finite value\(s\).*nan at step 3, dimension 2; fix or drop this demo",
    ),
    "an infinite state": (
        lambda p: _set(p, "data/demo_0/obs/robot0_eef_pos", lambda a: _with(a, (5, 1), np.inf)),
        r"demos\.hdf5:data/demo_0/obs/robot0_eef_pos has 1 non-finite value\(s\).*inf at step 5",
    ),
    "a state beyond float32": (
        lambda p: _set(p, "data/demo_1/obs/robot0_gripper_qpos", lambda a: _with(a.astype(np.float64), (0, 0), 1e39)),
        r"demos\.hdf5:data/demo_1/obs/robot0_gripper_qpos has 1 non-finite value\(s\) in float32",
    ),
    # Images are uint8 (T, H, W, 3) in this layout and so cannot hold a nan; float images, where one
    # could hide (and which would be scaled by 1/255 as if they were 0..255), are refused.
    "float images holding a nan": (
        lambda p: _set(p, "data/demo_1/obs/agentview_image", lambda a: _with(a.astype(np.float32), (0, 0, 0, 0), np.nan)),
        r"demos\.hdf5:data/demo_1/obs/agentview_image is float32 of shape \(10, 64, 64, 3\); images must be uint8",
    ),
    "images of another size in one demo": (
        _smaller_images_in_demo_1,
        r"demos\.hdf5:data/demo_1/obs/agentview_image has per-step shape \(32, 32, 3\) but .*demos\.hdf5:data/demo_0/obs/agentview_image has \(64, 64, 3\)",
    ),
    "actions shorter than the observations": (
        lambda p: _set(p, "data/demo_0/actions", lambda a: a[:9]),
        r"demos\.hdf5:data/demo_0/obs/agentview_image has 12 steps but the demo's actions have 9: .*repair or re-record",
    ),
    "a state longer than the actions": (
        lambda p: _set(p, "data/demo_1/obs/robot0_gripper_qpos", lambda a: np.concatenate([a, a[:1]])),
        r"demos\.hdf5:data/demo_1/obs/robot0_gripper_qpos has 11 steps but the demo's actions have 10",
    ),
    "actions of another width in one demo": (
        lambda p: _set(p, "data/demo_1/actions", lambda a: a[:, :6]),
        r"demos\.hdf5:data/demo_1/actions has per-step shape \(6,\) but .*demos\.hdf5:data/demo_0/actions has \(7,\)",
    ),
    "a missing state key": (
        lambda p: _delete(p, "data/demo_1/obs/robot0_eef_pos"),
        r"demos\.hdf5:data/demo_1/obs lacks \['robot0_eef_pos'\]",
    ),
    "a zero-byte file": (
        lambda p: p.write_bytes(b""),
        r"demos\.hdf5 is empty \(0 bytes\); re-record it or remove it",
    ),
    "a file with no demos": (
        _no_demos,
        r"demos\.hdf5:data holds no demonstration \(no `demo_N` group\)",
    ),
}  # fmt: skip


def _fit_refused(
    args: list[str], inputs: Path, out: Path, message: str, capfd: pytest.CaptureFixture[str]
) -> None:
    """``capvector fit`` exits 2 with one error line matching ``message``, before any run folder."""
    before = tree_digest(inputs)
    assert main(args) == 2
    err = capfd.readouterr().err
    errors = [line for line in err.splitlines() if "error" in line]
    assert "Traceback" not in err, err
    assert len(errors) == 1 and errors[0].startswith("capvector fit: error: "), errors
    assert re.search(message, errors[0]), errors[0]
    assert not out.exists(), sorted(out.rglob("*"))
    assert tree_digest(inputs) == before


@pytest.mark.parametrize("case", sorted(HDF5_CASES))
def test_bad_hdf5_is_refused_before_training(
    case: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    break_file, message = HDF5_CASES[case]
    inputs, out, cwd = tmp_path / "inputs", tmp_path / "out", tmp_path / "cwd"
    inputs.mkdir()
    cwd.mkdir()
    break_file(write_demo_file(inputs / "demos.hdf5"))
    monkeypatch.chdir(cwd)  # Lightning's default logger would write lightning_logs/ here
    args = [a for a in fit_args(inputs, out) if "logger" not in a]  # the default logger, as a user
    _fit_refused(args, inputs, out, message, capfd)
    assert not any(cwd.iterdir())


@pytest.mark.parametrize("where", ["data file", "stats.json"])
def test_non_finite_lerobot_values_are_refused_before_training(
    where: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from test_lerobot import CAMERAS as VIDEO_CAMERAS
    from test_lerobot import write_lerobot_v3

    root = tmp_path / "inputs"
    write_lerobot_v3(root)
    if where == "data file":
        path = root / "data/chunk-000/file-000.parquet"  # episodes 0 (9 frames) and 1
        table = pq.read_table(path)
        actions = np.stack(table.column("action").to_numpy(zero_copy_only=False))
        actions[11, 4] = np.nan  # episode 1, frame 2
        column = pa.FixedSizeListArray.from_arrays(pa.array(actions.reshape(-1)), 7)
        pq.write_table(
            table.set_column(table.schema.get_field_index("action"), "action", column), path
        )
        message = (
            r"file-000\.parquet: column 'action' has 1 non-finite value\(s\) in float32, the first "
            r"nan in episode 1, frame 2, dimension 4; fix the episode or leave it out"
        )
    else:
        stats = json.loads((root / "meta/stats.json").read_text())
        stats["observation.state"]["q99"][3] = float("inf")
        (root / "meta/stats.json").write_text(json.dumps(stats))
        message = r"meta/stats\.json: statistic proprio\.q99\[3\] is inf"
    out = tmp_path / "out"
    args = [
        a for a in fit_args(root, out) if not a.startswith("--data.train_files")
    ] + [f"--data.lerobot_root={root}", f"--data.cameras=[{','.join(VIDEO_CAMERAS)}]",
         "--data.proprio_keys=[observation.state]", "--data.chunk_size=3"]  # fmt: skip
    _fit_refused(args, root, out, message, capfd)


def test_statistics_refuse_non_finite_values(tmp_path: Path) -> None:
    actions = np.random.default_rng(0).normal(size=(20, 7))
    proprio = np.zeros((20, 2))
    entry = compute_statistics(actions, proprio, 2)
    check_finite_statistics({"lift": entry}, "ok")  # finite: accepted
    actions[4, 1] = np.nan
    with pytest.raises(CapVectorError, match=r"^the statistics computed from the data: statistic "):
        compute_statistics(actions, proprio, 2)
    entry["proprio"]["std"][1] = float("-inf")
    with pytest.raises(CapVectorError, match=r"^here: statistic lift\.proprio\.std\[1\] is -inf"):
        check_finite_statistics({"lift": entry}, "here")
    # The last guard: an export never writes them (nothing is left behind either).
    model = build_backbone("openvla-oft-tiny")
    with pytest.raises(CapVectorError, match=r"dataset_statistics\.json: statistic lift\.proprio"):
        model.save_pretrained(
            tmp_path / "export", extra_json={"dataset_statistics.json": {"lift": entry}}
        )
    assert not any(tmp_path.iterdir())
