"""Robot demonstrations in the robomimic / LIBERO HDF5 layout.

Layout read here (robomimic ``docs/datasets/overview.md``; LIBERO ``scripts/create_dataset.py``)::

    data/                      attrs: env_args (JSON), language_instruction or problem_info (LIBERO)
      demo_N/                  attrs: num_samples, language_instruction (optional)
        actions                (T, A)
        obs/<camera>_image     (T, H, W, 3) uint8, upright; LIBERO: obs/agentview_rgb,
                               obs/eye_in_hand_rgb (cameras agentview, robot0_eye_in_hand)
        obs/<camera>_depth     (T, H, W) float32 metres (optional); ours in LIBERO's files:
                               obs/agentview_depth, obs/eye_in_hand_depth
        obs/<proprio key>      (T, d) for each key in ``proprio_keys``, concatenated in order
        annotations            (T,) UTF-8 text about the scene (optional)

LIBERO's files (``data`` attr ``macros_image_convention="opengl"``) hold the images as the
simulator renders them; they are rotated 180 degrees when read, as the LIBERO evaluation rotates
the live images (``capvector.envs.libero.env.flip_image``; OpenVLA-OFT's RLDS conversion and
``get_libero_image``), so training and evaluation see the same orientation. Depth maps are rotated
with them, and the intrinsics (``data`` attrs ``<camera>_intrinsics``, of the frames as stored) are
rotated to match (:func:`rotate_intrinsics`), so depth back-projects to camera-frame points. Their 8-d proprio is
``proprio_keys: [ee_states, gripper_states]`` (eef position, axis-angle, two finger joints).

A sample is the observation at step t and the action chunk t..t+T-1. Chunks never run past the end
of an episode: as OFT (``chunk_act_obs``), only steps 0..len-T start a sample.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from capvector.data.batch import Sample
from capvector.data.statistics import BOUNDS_Q99, Normalizer, compute_statistics
from capvector.data.transforms import ImageTransform
from capvector.errors import CapVectorError

DEFAULT_CACHE_MB = 1024.0
"""Memory (MiB) for demo frames kept after their first read (``FrameCache``): 20 generated Lift
demos at 64 px take 26 MB (60 MB with depth); a LIBERO suite at 128 px (several GB) fills it and
the rest is read from the files, frame by frame."""


class DatasetError(CapVectorError):
    """A dataset file that does not have what the config asks for; the message says what to change."""


@dataclass
class EpisodeRef:
    file: int
    demo: str
    length: int
    instruction: str


def _demo_names(data: h5py.Group) -> list[str]:
    names = [k for k in data if k.startswith("demo_")]
    # demo_2 before demo_10; names without a number after them (a mixed sort would raise)
    return sorted(
        names, key=lambda k: (not k[5:].isdigit(), int(k[5:]) if k[5:].isdigit() else 0, k)
    )


def _instruction(data: h5py.Group, demo: h5py.Group, fallback: str | None, path: str) -> str:
    for attrs in (demo.attrs, data.attrs):
        if "language_instruction" in attrs:
            value = attrs["language_instruction"]
            return value.decode() if isinstance(value, bytes) else str(value)
    if "problem_info" in data.attrs:  # LIBERO keeps it inside a JSON attribute
        return json.loads(data.attrs["problem_info"])["language_instruction"]
    if fallback:
        return fallback
    raise DatasetError(
        f"{path} has no language instruction (attr `language_instruction` on `data` or the demo, "
        "or LIBERO's `problem_info`); set data.instruction in the config"
    )


def image_key(obs: h5py.Group, camera: str) -> str:
    """The key of ``camera``'s images in a demo's ``obs``: ``<camera>_image`` (robomimic, ours)
    or LIBERO's ``<camera>_rgb`` with robosuite's ``robot0_`` prefix dropped (``eye_in_hand_rgb``);
    ``<camera>_image`` when neither is there (the error names it)."""
    for key in (f"{camera}_image", f"{camera}_rgb", f"{camera.removeprefix('robot0_')}_rgb"):
        if key in obs:
            return key
    return f"{camera}_image"


def depth_key(obs: h5py.Group, camera: str) -> str:
    """The key of ``camera``'s depth in a demo's ``obs``: ``<camera>_depth``, or beside LIBERO's
    image keys without robosuite's ``robot0_`` prefix (``eye_in_hand_depth``, ``capvector demos
    --suite --depth``); ``<camera>_depth`` when neither is there (the error names it)."""
    for key in (f"{camera}_depth", f"{camera.removeprefix('robot0_')}_depth"):
        if key in obs:
            return key
    return f"{camera}_depth"


def rotate_intrinsics(intrinsics: np.ndarray, height: int, width: int) -> np.ndarray:
    """(..., 3, 3) intrinsics of images rotated 180 degrees: pixel coordinates (u, v) become
    (W - u, H - v) (continuous, pixel (i, j) covering [j, j+1) x [i, i+1)), so both focal lengths
    change sign and the principal point moves to (W - cx, H - cy)."""
    rotation = np.array([[-1.0, 0.0, width], [0.0, -1.0, height], [0.0, 0.0, 1.0]])
    return rotation @ intrinsics


def stored_upside_down(data: h5py.Group) -> bool:
    """LIBERO's ``create_dataset.py`` stores the renderer's OpenGL-convention frames and says so."""
    convention = data.attrs.get("macros_image_convention", "")
    return (convention.decode() if isinstance(convention, bytes) else str(convention)) == "opengl"


def _open(path: str) -> h5py.File:
    """``path`` opened for reading, or a DatasetError that says why it cannot be."""
    if not Path(path).is_file():
        raise DatasetError(f"dataset file {path} does not exist")
    if Path(path).stat().st_size == 0:
        raise DatasetError(
            f"{path} is empty (0 bytes); re-record it or remove it from the config's data files"
        )
    try:
        return h5py.File(path, "r")
    except OSError as exc:  # not HDF5, or truncated
        raise DatasetError(
            f"{path} is not a readable HDF5 file (h5py: {exc}); re-record or re-download it"
        ) from exc


def _check_steps(steps: int, length: int, key: str) -> None:
    if steps != length:
        raise DatasetError(
            f"{key} has {steps} steps but the demo's actions have {length}: every key of a demo "
            "needs one row per step; repair or re-record this demo"
        )


def _float32(values: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):  # beyond float32 becomes inf, which _check_finite names
        return np.asarray(values, np.float32)


def _check_finite(values: np.ndarray, key: str) -> None:
    """One nan in one demo would make the loss and the normalisation statistics nan."""
    bad = ~np.isfinite(values)
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        raise DatasetError(
            f"{key} has {int(bad.sum())} non-finite value(s) in float32, the first "
            f"{values[first]} at step {first[0]}, dimension {first[1]}; fix or drop this demo"
        )


class HDF5RobotDataset(Dataset):
    """Samples (observation at t, action chunk t..t+T-1) from one or more HDF5 files."""

    def __init__(
        self,
        files: Sequence[str | Path],
        cameras: Sequence[str],
        proprio_keys: Sequence[str],
        chunk_size: int,
        statistics: dict[str, Any] | None = None,
        transform: ImageTransform | None = None,
        instruction: str | None = None,
        load_depth: bool = False,
        load_annotations: bool = False,
        normalization: str = BOUNDS_Q99,
        cache_mb: float = DEFAULT_CACHE_MB,
    ) -> None:
        """``normalization`` is the rule of statistics computed here (``capvector.data.statistics``);
        given ``statistics`` carry their own. ``cache_mb``: memory for frames kept after their
        first read (see ``FrameCache``); 0 reads every frame from the file."""
        if not files:
            raise DatasetError("no dataset files given; set data.train_files")
        self.files = [str(f) for f in files]
        self.cameras = list(cameras)
        self.proprio_keys = list(proprio_keys)
        self.chunk_size = chunk_size
        self.transform = transform or ImageTransform(augment=False, center_crop=False)
        self.load_depth = load_depth
        self.load_annotations = load_annotations
        self.episodes: list[EpisodeRef] = []
        self.index: list[tuple[int, int]] = []  # (episode, start step)
        # kind ("actions", "image", ...) -> (per-step shape, the key it was first seen at)
        self._shapes: dict[str, tuple[tuple[int, ...], str]] = {}
        self._image_keys: list[list[str]] = []  # per file: each camera's obs key
        self._depth_keys: list[list[str]] = []  # per file: each camera's depth key
        self._upside_down: list[bool] = []  # per file: rotate its images 180 degrees when read
        all_actions, all_proprio = [], []
        for file_index, path in enumerate(self.files):
            with _open(path) as f:
                if "data" not in f:
                    raise DatasetError(f"{path} has no `data` group: not a robomimic/LIBERO file")
                data = f["data"]
                names = _demo_names(data)
                self._upside_down.append(stored_upside_down(data))
                first_obs = data[names[0]].get("obs", {}) if names else {}
                self._image_keys.append([image_key(first_obs, c) for c in self.cameras])
                self._depth_keys.append([depth_key(first_obs, c) for c in self.cameras])
                if not names:
                    raise DatasetError(
                        f"{path}:data holds no demonstration (no `demo_N` group); re-record the "
                        "file or remove it from the config's data files"
                    )
                for name in names:
                    demo = data[name]
                    actions, proprio = self._read_demo(demo, path, name)
                    length = actions.shape[0]
                    episode = EpisodeRef(
                        file_index, name, length, _instruction(data, demo, instruction, path)
                    )
                    if length < chunk_size:
                        continue  # too short for one full chunk; OFT drops such windows as well
                    self.episodes.append(episode)
                    ep = len(self.episodes) - 1
                    self.index.extend((ep, t) for t in range(length - chunk_size + 1))
                    all_actions.append(actions)
                    all_proprio.append(proprio)
        if not self.index:
            raise DatasetError(
                f"{self.files} hold no episode of at least chunk_size={chunk_size} steps"
            )
        with h5py.File(self.files[0], "r") as f:
            attrs = f["data"].attrs
            height = self._shapes["image"][0][0]
            self.image_size = int(attrs.get("image_size", height))
            self.camera_fovy = json.loads(attrs["camera_fovy"]) if "camera_fovy" in attrs else None
        self.action_dim = all_actions[0].shape[1]
        self.proprio_dim = all_proprio[0].shape[1]
        self.statistics = statistics or compute_statistics(
            np.concatenate(all_actions),
            np.concatenate(all_proprio),
            len(self.episodes),
            normalization=normalization,
        )
        self.normalizer = Normalizer(self.statistics)
        # Actions and proprio are small (a few floats a step): kept normalised for every episode,
        # a sample slices them instead of reading its keys from the file.
        self._actions = [self.normalizer.normalize("action", _float32(a)) for a in all_actions]
        self._proprio = [self.normalizer.normalize("proprio", p) for p in all_proprio]
        self._cache = FrameCache(cache_mb)
        self._handles: dict[int, h5py.File] = {}
        self.intrinsics = [self._read_intrinsics(path) for path in self.files] if load_depth else []

    def _read_intrinsics(self, path: str) -> torch.Tensor:
        """(N_cam, 3, 3) from ``data`` attrs ``<camera>_intrinsics`` (written by ``capvector demos``)."""
        with h5py.File(path, "r") as f:
            attrs = f["data"].attrs
            missing = [c for c in self.cameras if f"{c}_intrinsics" not in attrs]
            if missing:
                raise DatasetError(
                    f"{path} has depth but no camera intrinsics for {missing} (attr "
                    "`data.<camera>_intrinsics`, 3x3 in pixels); regenerate with `capvector demos --depth`"
                )
            intrinsics = np.stack([attrs[f"{c}_intrinsics"] for c in self.cameras])
            if stored_upside_down(f["data"]):  # the frames are rotated when read: these too
                height, width, _ = self._shapes["image"][0]
                intrinsics = rotate_intrinsics(intrinsics, height, width)
            return torch.tensor(intrinsics, dtype=torch.float32)

    def _check_demo(self, demo: h5py.Group, path: str, name: str) -> None:
        where = f"{path}:data/{name}"
        if "actions" not in demo:
            raise DatasetError(f"{where} has no `actions` dataset")
        obs = demo.get("obs")
        available = sorted(obs.keys()) if obs is not None else []
        depth = (
            [depth_key(obs, c) for c in self.cameras] if self.load_depth and obs is not None else []
        )
        missing_depth = [k for k in depth if k not in available]
        images = [image_key(obs, c) for c in self.cameras] if obs is not None else []
        missing = [k for k in images + self.proprio_keys if k not in available]
        if missing_depth and not missing:
            raise DatasetError(
                f"{where}/obs has no depth ({missing_depth}): the demos were recorded without "
                "depth, which this config loads (for spatial alignment). Record them with "
                "`capvector demos --depth`, or set data.load_depth=false"
            )
        if missing:
            raise DatasetError(
                f"{where}/obs lacks {missing}; it has {available}. Set data.cameras (without the "
                "`_image` suffix) and data.proprio_keys to keys the file has"
            )
        if self.load_annotations and "annotations" not in demo:
            raise DatasetError(
                f"{where} has no `annotations`; regenerate the demos or set load_annotations=false"
            )

    def _read_demo(self, demo: h5py.Group, path: str, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(T, A) actions and (T, P) proprio of one demo, read once for the statistics and checked
        on the way: every key the config reads has one row per step and the same per-step shape as
        in the first demo (one image size for every camera), and the numbers are finite in
        float32. A bad demo is named here, before training, not met as a nan loss or a collate
        error mid-run. Images and depth are checked from their metadata only (no pixel is read)."""
        self._check_demo(demo, path, name)
        where = f"{path}:data/{name}"
        actions = demo["actions"][()]  # as stored: the statistics are computed from these
        if actions.ndim != 2:
            raise DatasetError(
                f"{where}/actions has shape {actions.shape}; actions must be (T, A): repair or "
                "re-record this demo"
            )
        length = actions.shape[0]
        _check_finite(_float32(actions), f"{where}/actions")  # what the model trains on
        self._check_shape("actions", actions.shape[1:], f"{where}/actions")
        obs = demo["obs"]
        for camera in self.cameras:
            image = obs[image_key(obs, camera)]
            key = f"{where}/obs/{image_key(obs, camera)}"
            if image.dtype != np.uint8 or image.ndim != 4 or image.shape[-1] != 3:
                raise DatasetError(
                    f"{key} is {image.dtype} of shape {image.shape}; images must be uint8 "
                    "(T, H, W, 3) RGB, as robomimic and LIBERO store them: convert the file"
                )
            _check_steps(image.shape[0], length, key)
            self._check_shape("image", image.shape[1:], key)
            if self.load_depth:  # (T, H, W): the images' size, so both follow one crop
                depth = obs[depth_key(obs, camera)]
                self._shapes.setdefault("depth", (image.shape[1:3], key))
                key = f"{where}/obs/{depth_key(obs, camera)}"
                _check_steps(depth.shape[0], length, key)
                self._check_shape("depth", depth.shape[1:], key)
        if self.load_annotations:
            _check_steps(demo["annotations"].shape[0], length, f"{where}/annotations")
        parts = [np.zeros((length, 0), np.float32)]
        for feature in self.proprio_keys:
            key = f"{where}/obs/{feature}"
            values = np.atleast_1d(_float32(obs[feature][()]))
            _check_steps(values.shape[0], length, key)
            values = values.reshape(length, math.prod(values.shape[1:]))
            _check_finite(values, key)
            self._check_shape(f"obs/{feature}", values.shape[1:], key)
            parts.append(values)
        return actions, np.concatenate(parts, axis=-1)

    def _check_shape(self, kind: str, shape: tuple[int, ...], key: str) -> None:
        """Every demo's per-step ``shape`` of ``kind`` is the first demo's: samples are stacked."""
        first, first_key = self._shapes.setdefault(kind, (shape, key))
        if shape != first:
            raise DatasetError(
                f"{key} has per-step shape {shape} but {first_key} has {first}: every demo (and "
                "every camera) needs the same shape; resize or drop the odd demos, or train on "
                "them separately"
            )

    def __len__(self) -> int:
        return len(self.index)

    def annotations(self) -> Iterator[str]:
        """Every step's annotation of every episode, the text the reasoning objective scores (read
        with handles of its own, so none is left open across a DataLoader worker's fork)."""
        if not self.load_annotations:
            raise DatasetError(
                "this dataset does not load annotations: set data.load_annotations=true"
            )
        for file_index, path in enumerate(self.files):
            with _open(path) as f:
                for episode in self.episodes:
                    if episode.file == file_index:
                        for text in f["data"][episode.demo]["annotations"][:]:
                            yield text.decode() if isinstance(text, bytes) else str(text)

    def _file(self, index: int) -> h5py.File:
        # One handle per process: h5py handles must not cross a DataLoader worker fork.
        if index not in self._handles:
            self._handles[index] = h5py.File(self.files[index], "r")
        return self._handles[index]

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_handles"] = {}
        state["_cache"] = FrameCache(self._cache.limit / 2**20)  # a worker fills its own
        return state

    def __getitem__(self, i: int) -> Sample:
        return self.__getitems__([i])[0]

    def __getitems__(self, indices: Sequence[int]) -> list[Sample]:
        """The samples at ``indices``: the DataLoader asks for a batch's samples at once, so the
        image transform runs once over all their images (``ImageTransform.batch``)."""
        frames = [self._frames(i) for i in indices]
        cameras = len(self.cameras)
        height, width, _ = self._shapes["image"][0]
        pixels = np.concatenate([f.images for f in frames]).reshape(-1, height, width, 3)
        depth = intrinsics = None
        if self.load_depth:  # (B·N_cam, H, W) and (B·N_cam, 3, 3), as the images
            stacked = np.concatenate([f.depth for f in frames])  # type: ignore[misc]
            depth = torch.from_numpy(stacked.reshape(-1, height, width))
            intrinsics = torch.cat([self.intrinsics[f.file] for f in frames])
        images, depth, intrinsics = self.transform.batch(
            torch.from_numpy(pixels).permute(0, 3, 1, 2).contiguous(), depth, intrinsics
        )
        samples = []
        for b, (i, f) in enumerate(zip(indices, frames, strict=True)):
            ep_index, t = self.index[i]
            episode = self.episodes[ep_index]
            views = slice(b * cameras, (b + 1) * cameras)
            sample: Sample = {
                "images": images[views],
                "proprio": torch.from_numpy(self._proprio[ep_index][t]),
                "actions": torch.from_numpy(self._actions[ep_index][t : t + self.chunk_size]),
                "instruction": episode.instruction,
                "index": i,
            }
            if self.load_depth:
                sample["depth"] = depth[views]  # type: ignore[index]
                sample["intrinsics"] = intrinsics[views]  # type: ignore[index]
            if self.load_annotations:
                sample["annotation"] = f.annotation
            samples.append(sample)
        return samples

    def _frames(self, i: int) -> Frames:
        """Sample ``i``'s frames, from the cache, else from the file (whole episode when the cache
        has room for it)."""
        ep_index, t = self.index[i]
        episode = self.episodes[ep_index]
        cached = self._cache.get(ep_index)
        if cached is None and self._cache.has_room(self._episode_bytes(episode)):
            cached = self._cache.put(ep_index, self._read_frames(episode, slice(None)))
        if cached is not None:
            return cached.at(t)
        return self._read_frames(episode, slice(t, t + 1))

    def _episode_bytes(self, episode: EpisodeRef) -> int:
        height, width, _ = self._shapes["image"][0]
        per_step = height * width * (3 + 4 * self.load_depth) * len(self.cameras)
        return per_step * episode.length

    def _read_frames(self, episode: EpisodeRef, steps: slice) -> Frames:
        """The frames (images, depth, annotations the config loads) at ``steps`` of one episode."""
        demo = self._file(episode.file)["data"][episode.demo]
        obs = demo["obs"]
        keys = self._image_keys[episode.file]
        images = np.stack([obs[key][steps] for key in keys], axis=1)
        depth = (
            np.stack([obs[key][steps] for key in self._depth_keys[episode.file]], axis=1).astype(
                np.float32
            )
            if self.load_depth
            else None
        )
        if self._upside_down[episode.file]:  # (S, N_cam, H, W[, 3]): each frame rotated 180°
            images = np.ascontiguousarray(images[:, :, ::-1, ::-1])
            if depth is not None:
                depth = np.ascontiguousarray(depth[:, :, ::-1, ::-1])
        annotations = demo["annotations"][steps] if self.load_annotations else None
        return Frames(episode.file, images, depth, annotations)


@dataclass
class Frames:
    """Frames of one episode: S steps of all cameras (S = 1 for one sample)."""

    file: int
    images: np.ndarray
    """(S, N_cam, H, W, 3) uint8, as stored."""
    depth: np.ndarray | None
    """(S, N_cam, H, W) float32 metres, or None."""
    annotations: np.ndarray | None
    """(S,) text (bytes or str), or None."""

    def at(self, t: int) -> Frames:
        """Step ``t`` alone (S = 1), as views."""
        return Frames(
            self.file,
            self.images[t : t + 1],
            None if self.depth is None else self.depth[t : t + 1],
            None if self.annotations is None else self.annotations[t : t + 1],
        )

    @property
    def annotation(self) -> str:
        text = self.annotations[0]  # type: ignore[index]
        return text.decode() if isinstance(text, bytes) else str(text)


class FrameCache:
    """Episodes' frames kept in memory after their first read, up to ``limit_mb``.

    Reading a frame from a demo file costs HDF5 lookups and a gzip decode per key (``capvector
    demos`` compresses images and depth), a share of a tiny model's step; once cached, a sample is
    an array slice. Episodes
    are kept as they are first read until the limit is reached; the others are then read frame by
    frame from the file, as without a cache (no eviction: with samples drawn at random, evicting
    would read whole episodes for single frames). The limit is per process: each DataLoader
    worker keeps its own cache."""

    def __init__(self, limit_mb: float) -> None:
        if limit_mb < 0:
            raise DatasetError(f"data.cache_mb is {limit_mb}; give 0 (no cache) or more")
        self.limit = int(limit_mb * 2**20)
        self.used = 0
        self._episodes: dict[int, Frames] = {}

    def get(self, episode: int) -> Frames | None:
        return self._episodes.get(episode)

    def has_room(self, nbytes: int) -> bool:
        return self.used + nbytes <= self.limit

    def put(self, episode: int, frames: Frames) -> Frames:
        self._episodes[episode] = frames
        self.used += frames.images.nbytes + (0 if frames.depth is None else frames.depth.nbytes)
        return frames
