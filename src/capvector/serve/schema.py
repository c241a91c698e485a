"""What a served policy accepts: the observation schema, checked before anything reaches the model.

A request is one msgpack map (``capvector.serve.wire``) in either spelling, mixed freely:

============================  ===================================  ==============================
slot                          ours (``VLAPolicy``'s observation)   openpi's LIBERO example client
============================  ===================================  ==============================
camera ``cameras[0]``         ``images: {camera: image}``          ``observation/image``
camera ``cameras[1]``         ``images: {camera: image}``          ``observation/wrist_image``
further cameras               ``images: {camera: image}``          (none)
proprio, raw (P,)             ``proprio``                          ``observation/state``
instruction                   ``instruction``                      ``prompt``
============================  ===================================  ==============================

The camera order and P are the export's (``DataSpec.cameras``, ``proprio_dim``); openpi's keys
follow ``examples/libero/main.py`` (agentview image, wrist image, eef pos + axis-angle + 2 gripper
joints = 8, task language), which matches our LIBERO cameras ``agentview``, ``robot0_eye_in_hand``.

- An image is a numpy ``uint8`` array (H, W, 3), RGB, upright as the training images were stored
  (LIBERO's clients rotate them 180 degrees first, as openpi's does). All cameras of a request
  have one size; any size is accepted and the backbone resizes it as its own preprocessing does
  (the export's ``image_size`` is what training saw: send that size).
- ``proprio`` is a real-valued (P,) array or list, raw (the server normalises it with the export's
  statistics), every value finite.
- ``instruction`` is a string; the server's ``--default-prompt`` stands in for a missing one.

What one request may cost is bounded, so one client cannot hold the forward for everyone (an
8,000,000 x 1 image took 89 s to preprocess, a 64 KB prompt asked for 26 GB in the forward): an
image has at most ``max_image_pixels`` pixels and a long side at most ``max_aspect`` times its
short side; an instruction has at most ``max_prompt_tokens`` tokens of the policy's tokenizer
(counted only when its length in characters could fit; without a tokenizer, characters count).
A message larger than these bounds allow closes its connection unread (``max_message_bytes``).

Anything else in the map is ignored. A request that breaks a rule gets one line back naming the
key and what is wrong (``ObservationError``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from capvector.data.spec import DataSpec
from capvector.errors import CapVectorError

OPENPI_IMAGE_KEYS = ("observation/image", "observation/wrist_image")
"""openpi's LIBERO client's images, by camera position."""
OPENPI_STATE_KEY = "observation/state"
OPENPI_PROMPT_KEY = "prompt"
IMAGES, PROPRIO, INSTRUCTION = "images", "proprio", "instruction"
MAX_IMAGE_PIXELS = 1024 * 1024
"""Default bound on an image's H x W: a megapixel, 16x what LIBERO renders (256 x 256); openpi's
clients resize to 224 x 224 before sending."""
MAX_ASPECT = 4.0
"""Default bound on an image's long side over its short side (cameras are 4:3 or 16:9)."""
MAX_PROMPT_TOKENS = 256
"""Default bound on an instruction's tokens (LIBERO's run to about 20)."""
MESSAGE_SLACK = 2**20
"""Bytes of a request beyond its images' pixels: state, instruction, msgpack framing."""
CHARS_PER_TOKEN = 16
"""A prompt longer than this many characters per allowed token is refused without tokenizing it."""

Observation = dict[str, Any]
"""``{"images": {camera: uint8 (H, W, 3)}, "proprio": float32 (P,), "instruction": str}``: what
``VLAPolicy`` takes."""


class ObservationError(CapVectorError):
    """A request the schema refuses; its message goes back to the client."""


@dataclass(frozen=True)
class ObservationSchema:
    cameras: tuple[str, ...]
    proprio_dim: int
    default_prompt: str | None = None
    max_image_pixels: int = MAX_IMAGE_PIXELS
    max_aspect: float = MAX_ASPECT
    max_prompt_tokens: int = MAX_PROMPT_TOKENS
    count_tokens: Callable[[str], int] = field(default=len, compare=False)
    """The policy's token count of an instruction (default: its characters)."""

    @classmethod
    def of(
        cls, spec: DataSpec, default_prompt: str | None = None, **bounds: Any
    ) -> ObservationSchema:
        """The schema of a policy trained on ``spec``; ``bounds``: the ``max_*`` and
        ``count_tokens`` fields."""
        return cls(tuple(spec.cameras), spec.proprio_dim, default_prompt, **bounds)

    @property
    def max_message_bytes(self) -> int:
        """The largest request the bounds let through; a bigger message closes its connection
        (1009, too big) before it is read, so a 50 MB one costs the server nothing (openpi sets
        no limit)."""
        return len(self.cameras) * self.max_image_pixels * 3 + MESSAGE_SLACK

    def key_map(self) -> dict[str, str]:
        """openpi's key -> our slot, as the metadata message tells clients."""
        mapping = {
            key: f"images/{cam}" for key, cam in zip(OPENPI_IMAGE_KEYS, self.cameras, strict=False)
        }
        return {**mapping, OPENPI_STATE_KEY: PROPRIO, OPENPI_PROMPT_KEY: INSTRUCTION}

    def parse(self, request: Any) -> Observation:
        """The checked observation of one request, or ``ObservationError`` naming what is wrong."""
        if not isinstance(request, Mapping):
            raise ObservationError(f"a request is a map of observation keys, got {_kind(request)}")
        images = request.get(IMAGES, {})
        if not isinstance(images, Mapping):
            raise ObservationError(f"{IMAGES!r} is a map {{camera: image}}, got {_kind(images)}")
        parsed = {}
        for index, camera in enumerate(self.cameras):
            spellings = [(f"{IMAGES}/{camera}", images, camera)]
            if index < len(OPENPI_IMAGE_KEYS):
                spellings.append((OPENPI_IMAGE_KEYS[index], request, OPENPI_IMAGE_KEYS[index]))
            parsed[camera] = self._image(*_pick(request, spellings))
        shapes = {camera: image.shape for camera, image in parsed.items()}
        if len(set(shapes.values())) > 1:
            raise ObservationError(f"the cameras' images differ in size: {shapes}; send one size")
        state = _pick(request, [(k, request, k) for k in (PROPRIO, OPENPI_STATE_KEY)])
        prompts = [(k, request, k) for k in (INSTRUCTION, OPENPI_PROMPT_KEY)]
        if self.default_prompt is not None and not any(k in request for _, _, k in prompts):
            instruction = self.default_prompt
        else:
            name, instruction = _pick(request, prompts, "or start the server with --default-prompt")
            if not isinstance(instruction, str):
                raise ObservationError(f"{name!r} is a string, got {_kind(instruction)}")
            self._check_prompt(name, instruction)
        return {IMAGES: parsed, PROPRIO: _state(*state, self.proprio_dim), INSTRUCTION: instruction}

    def _check_prompt(self, name: str, prompt: str) -> None:
        limit = self.max_prompt_tokens
        if len(prompt) > limit * CHARS_PER_TOKEN:  # not worth tokenizing
            raise ObservationError(
                f"{name!r} has {len(prompt)} characters; this server takes instructions of at "
                f"most {limit} tokens: send a shorter one"
            )
        if (tokens := self.count_tokens(prompt)) > limit:
            raise ObservationError(
                f"{name!r} has {tokens} tokens; this server takes at most {limit}: send a "
                "shorter instruction"
            )

    def _image(self, name: str, value: Any) -> np.ndarray:
        image = _image(name, value)
        height, width = image.shape[:2]
        if height * width > self.max_image_pixels:
            raise ObservationError(
                f"{name!r} has {height} x {width} = {height * width} pixels; this server takes "
                f"at most {self.max_image_pixels}: send the metadata's image_size"
            )
        if max(height, width) > self.max_aspect * min(height, width):
            raise ObservationError(
                f"{name!r} is {height} x {width}, more than {self.max_aspect:g}:1; send the "
                "camera's image, e.g. at the metadata's image_size"
            )
        return np.array(image)  # a writable copy: the message's array is a read-only view


def _pick(
    request: Mapping[str, Any], spellings: list[tuple[str, Mapping[str, Any], str]], hint: str = ""
) -> tuple[str, Any]:
    """``(name, value)`` of the one spelling of a slot the request uses; each spelling is
    ``(name, the map it is looked up in, its key there)``."""
    present = [(name, where[key]) for name, where, key in spellings if key in where]
    if len(present) > 1:
        raise ObservationError(f"both {present[0][0]!r} and {present[1][0]!r} given; send one")
    if not present:
        names = " or ".join(repr(name) for name, _, _ in spellings)
        raise ObservationError(
            f"missing {names}" + (f" ({hint})" if hint else "") + f"; got keys {_keys(request)}"
        )
    return present[0]


def _image(name: str, value: Any) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        raise ObservationError(f"{name!r} is a numpy uint8 array (H, W, 3), got {_kind(value)}")
    if value.dtype != np.uint8:
        raise ObservationError(
            f"{name!r} has dtype {value.dtype}; send uint8 (0-255), e.g. through "
            "openpi_client.image_tools.convert_to_uint8"
        )
    if value.ndim != 3 or value.shape[-1] != 3 or 0 in value.shape:
        raise ObservationError(
            f"{name!r} has shape {value.shape}; send one RGB image (H, W, 3), channels last"
        )
    return value


def _state(name: str, value: Any, dim: int) -> np.ndarray:
    try:
        array = np.asarray(value) if isinstance(value, np.ndarray | list | tuple) else None
    except ValueError:  # a ragged list
        array = None
    if array is None or array.dtype.kind not in "fiu":
        got = _kind(value) if array is None else f"an array of {array.dtype}"
        raise ObservationError(f"{name!r} is a real-valued ({dim},) array, got {got}")
    if array.shape != (dim,):
        raise ObservationError(f"{name!r} has shape {array.shape}; this policy takes ({dim},)")
    state = array.astype(np.float32)  # what the model sees: a float64 beyond float32 is inf
    bad = np.flatnonzero(~np.isfinite(state))
    if bad.size:
        raise ObservationError(
            f"{name!r} has non-finite values at {bad.tolist()}: {array[bad].tolist()}"
        )
    return state


def _keys(request: Mapping[str, Any]) -> str:
    return "[" + ", ".join(repr(k) for k in request) + "]"


def _kind(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"an array of {value.dtype} {value.shape}"
    return f"a {type(value).__name__}"
