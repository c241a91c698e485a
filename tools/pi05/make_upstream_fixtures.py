"""Write the Pi0.5 parity fixtures with LeRobot's own pi05 code (tests/fixtures/upstream/pi05/).

Runs in a scratch environment that has the upstream code, never in capvector's: it imports
``lerobot`` (PyPI ``lerobot==0.4.4``) and nothing from capvector. LeRobot 0.4.4's pi05 needs the
transformers that openpi patches (``src/openpi/models_pytorch/transformers_replace``, applied to
``transformers==4.53.2``, as openpi's README and LeRobot 0.4.4's ``pip install lerobot[pi]`` do); the
openpi checkout whose patch was applied is passed with ``--openpi`` and recorded in PROVENANCE.

    python tools/pi05/make_upstream_fixtures.py --openpi /path/to/openpi --out tests/fixtures/upstream/pi05

What it writes for the variant ``lerobot`` (a tiny PI05Policy with random weights from a fixed seed):

- the policy folder exactly as LeRobot writes it: ``policy.save_pretrained`` (``config.json`` +
  ``model.safetensors``) and the processors' ``save_pretrained`` (``policy_preprocessor.json``,
  ``policy_postprocessor.json`` and their normaliser ``.safetensors`` holding the statistics);
- ``tokenizer/``: a byte-level stand-in for PaliGemma's tokenizer (the hub is unreachable here),
  which LeRobot's ``TokenizerProcessorStep`` loads in place of ``google/paligemma-3b-pt-224``;
- ``reference.safetensors``: a fixed raw batch and what LeRobot computes from it (normalised state
  and actions, prompt tokens, SigLIP features, projected image features, prefix hidden states,
  actions sampled from fixed noise, raw actions after the postprocessor, the per-element training
  loss at fixed noise and time).

Sizes are patched here because LeRobot has no tiny variant: ``get_gemma_config`` returns toy Gemma
widths and the PaliGemma/Gemma HF configs it builds get a small vocabulary and a toy SigLIP (the
values LeRobot assigns over them, e.g. ``intermediate_size = 4304``, are pinned to ours). LeRobot's
attention hard-codes 8 query heads, so both toy streams keep 8.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import torch

SEED = 0
VOCAB = 272
IMAGE = 32
RAW_IMAGE = 48  # square, so resizing runs but no padding (see the PROVENANCE note on padding)
VLM = {"width": 64, "depth": 2, "mlp_dim": 128, "num_heads": 8, "num_kv_heads": 1, "head_dim": 16}
EXPERT = {"width": 32, "depth": 2, "mlp_dim": 64, "num_heads": 8, "num_kv_heads": 1, "head_dim": 16}
VISION = {
    "hidden_size": 32,
    "intermediate_size": 64,
    "num_hidden_layers": 2,
    "num_attention_heads": 4,
    "patch_size": 8,
}
CHUNK, ACTION_DIM, STATE_DIM, STEPS = 5, 7, 8, 4
CAMERAS = ("observation.images.base_0_rgb", "observation.images.left_wrist_0_rgb")
TASKS = ["pick up the red_block\n", "  open the top drawer"]


def pinned(config, **values):
    """``config`` whose fields in ``values`` keep these values whatever is assigned later."""
    base = type(config)

    def __setattr__(self, key, value):  # noqa: N807
        super(cls, self).__setattr__(key, values.get(key, value))

    cls = type("Pinned" + base.__name__, (base,), {"__setattr__": __setattr__})
    config.__class__ = cls
    for key, value in values.items():
        setattr(config, key, value)
    return config


def patch_hf_sizes(module, vision: dict) -> None:
    """Toy HF configs in ``module`` (LeRobot ``modeling_pi05`` or openpi ``gemma_pytorch``), whose
    ``PaliGemmaWithExpertModel`` builds them through ``CONFIG_MAPPING`` and then assigns full-size
    values (vocab 257152, SigLIP MLP 4304, projection 2048) that the pins keep at ours."""
    from transformers import GemmaConfig, PaliGemmaConfig, PaliGemmaForConditionalGeneration

    def paligemma(**kwargs):
        config = PaliGemmaConfig(**kwargs)
        config.vision_config = pinned(config.vision_config, **vision, projection_dim=VLM["width"])
        config.text_config = pinned(config.text_config, vocab_size=VOCAB)
        return config

    def gemma(**kwargs):
        return GemmaConfig(**{**kwargs, "vocab_size": VOCAB})

    def build_paligemma(config):
        # Pinning is over once upstream has assigned its values: HF maps config classes to models.
        for sub in (config.vision_config, config.text_config):
            sub.__class__ = type(sub).__mro__[1]
        return PaliGemmaForConditionalGeneration(config=config)

    module.PaliGemmaForConditionalGeneration = build_paligemma
    module.CONFIG_MAPPING = {"paligemma": paligemma, "gemma": gemma}


def patch_sizes() -> None:
    from lerobot.policies.pi05 import modeling_pi05

    def gemma_config(variant: str):
        spec = {"gemma_2b": VLM, "gemma_300m": EXPERT}[variant]
        return modeling_pi05.GemmaConfig(**spec)

    modeling_pi05.get_gemma_config = gemma_config
    patch_hf_sizes(modeling_pi05, VISION)


def write_tokenizer(folder: Path) -> None:
    """Byte-level BPE without merges: every UTF-8 byte is one token; PaliGemma's special ids
    (<pad> 0, <eos> 1, <bos> 2) and a BOS prepended by the post-processor."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    alphabet = pre_tokenizers.ByteLevel.alphabet()
    vocab = {"<pad>": 0, "<eos>": 1, "<bos>": 2}
    for char in sorted(alphabet):
        vocab[char] = len(vocab)
    tok = Tokenizer(models.BPE(vocab=vocab, merges=[]))
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False)
    tok.decoder = decoders.ByteLevel()
    tok.post_processor = processors.TemplateProcessing(
        single="<bos> $A", pair="<bos> $A $B", special_tokens=[("<bos>", 2)]
    )
    fast = PreTrainedTokenizerFast(
        tokenizer_object=tok, bos_token="<bos>", eos_token="<eos>", pad_token="<pad>"
    )
    fast.save_pretrained(str(folder))


def randomize(module: torch.nn.Module, generator: torch.Generator) -> None:
    """Every parameter random (LeRobot zero-inits the adaRMS weights, which would hide the time
    conditioning): N(0, 1/fan_in) for matrices, N(0, 0.1) for vectors."""
    with torch.no_grad():
        for _name, p in sorted(module.named_parameters()):
            std = p[0].numel() ** -0.5 if p.ndim > 1 else 0.1
            p.copy_(torch.randn(p.shape, generator=generator) * std)


def statistics() -> dict[str, dict[str, torch.Tensor]]:
    g = torch.Generator().manual_seed(SEED + 1)

    def stats(dim: int) -> dict[str, torch.Tensor]:
        q01 = -1 - torch.rand(dim, generator=g)
        q99 = 1 + torch.rand(dim, generator=g)
        return {
            "mean": (q01 + q99) / 2,
            "std": (q99 - q01) / 4,
            "min": q01 - 0.5,
            "max": q99 + 0.5,
            "q01": q01,
            "q99": q99,
            "count": torch.tensor([1000]),
        }

    return {"observation.state": stats(STATE_DIM), "action": stats(ACTION_DIM)}


def raw_batch(stats) -> dict[str, object]:
    g = torch.Generator().manual_seed(SEED + 2)
    batch: dict[str, object] = {
        key: torch.rand(2, 3, RAW_IMAGE, RAW_IMAGE, generator=g) for key in CAMERAS
    }
    q01, q99 = stats["observation.state"]["q01"], stats["observation.state"]["q99"]
    state = q01 + (q99 - q01) * torch.rand(2, STATE_DIM, generator=g)
    state[0, 0] = q01[0] - 0.3  # normalises below -1: digitize gives bin -1 upstream
    state[1, 1] = q99[1] + 0.3  # above 1: bin 255
    state[1, 2] = q01[2]  # exactly -1
    batch["observation.state"] = state
    a01, a99 = stats["action"]["q01"], stats["action"]["q99"]
    actions = a01 + (a99 - a01) * (torch.rand(2, CHUNK, ACTION_DIM, generator=g) * 1.4 - 0.2)
    batch["action"] = actions  # some outside [q01, q99]: normalised beyond [-1, 1], not clipped
    batch["task"] = list(TASKS)
    return batch


def make_lerobot(out: Path, openpi: Path) -> None:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.pi05.configuration_pi05 import PI05Config
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy
    from lerobot.policies.pi05.processor_pi05 import make_pi05_pre_post_processors
    from lerobot.processor import tokenizer_processor
    from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS

    patch_sizes()
    out.mkdir(parents=True, exist_ok=True)
    tokenizer_dir = out / "tokenizer"
    write_tokenizer(tokenizer_dir)
    auto = tokenizer_processor.AutoTokenizer

    class StandInTokenizer:
        @staticmethod
        def from_pretrained(name, *args, **kwargs):
            assert name == "google/paligemma-3b-pt-224", name
            return auto.from_pretrained(str(tokenizer_dir))

    tokenizer_processor.AutoTokenizer = StandInTokenizer

    config = PI05Config(
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        num_inference_steps=STEPS,
        image_resolution=(IMAGE, IMAGE),
        device="cpu",
        dtype="float32",
        input_features={
            **{key: PolicyFeature(FeatureType.VISUAL, (3, IMAGE, IMAGE)) for key in CAMERAS},
            "observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
    )
    torch.manual_seed(SEED)
    policy = PI05Policy(config)
    randomize(policy, torch.Generator().manual_seed(SEED))
    policy.eval()
    stats = statistics()
    pre, post = make_pi05_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(str(out))
    pre.save_pretrained(str(out))
    post.save_pretrained(str(out))

    batch = raw_batch(stats)
    refs: dict[str, torch.Tensor] = {
        f"input.image.{i}": batch[key] for i, key in enumerate(CAMERAS)
    }
    refs["input.state"] = batch["observation.state"].clone()
    refs["input.actions"] = batch["action"].clone()
    processed = pre(dict(batch))
    refs["normalized.state"] = processed["observation.state"]
    refs["normalized.actions"] = processed["action"]
    refs["tokens"] = processed[OBS_LANGUAGE_TOKENS]
    refs["token_mask"] = processed[OBS_LANGUAGE_ATTENTION_MASK].to(torch.bool)

    model = policy.model
    images, img_masks = policy._preprocess_images(processed)
    paligemma = model.paligemma_with_expert.paligemma
    with torch.no_grad():
        siglip = [paligemma.model.vision_tower(img).last_hidden_state for img in images]
        refs["siglip"] = torch.stack(siglip, dim=1)  # (B, N_cam, patches, W_vision)
        features = [model.paligemma_with_expert.embed_image(img) for img in images]
        refs["image_features"] = torch.stack(features, dim=1)  # (B, N_cam, patches, W_vlm)
        tokens, masks = refs["tokens"], processed[OBS_LANGUAGE_ATTENTION_MASK]
        prefix, _, _ = model.embed_prefix(images, img_masks, tokens, masks)
        refs["hidden.0"] = prefix

        hidden: dict[int, torch.Tensor] = {}
        layers = paligemma.language_model.layers

        def keep(index: int):
            def hook(_module, _args, output) -> None:  # returns None: the output is unchanged
                hidden.setdefault(index, output[0] if isinstance(output, tuple) else output)

            return hook

        handles = [layer.register_forward_hook(keep(i + 1)) for i, layer in enumerate(layers)]
        noise = torch.randn(
            2, CHUNK, config.max_action_dim, generator=torch.Generator().manual_seed(3)
        )
        refs["sample.noise"] = noise
        sampled = model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone())
        for handle in handles:
            handle.remove()
        for index, value in hidden.items():
            refs[f"hidden.{index}"] = value
        refs["sample.actions"] = sampled  # (B, T, max_action_dim), normalised
        refs["sample.actions_raw"] = post(sampled[:, :, :ACTION_DIM].clone())

        loss_noise = torch.randn(
            2, CHUNK, config.max_action_dim, generator=torch.Generator().manual_seed(4)
        )
        loss_time = torch.tensor([0.3, 0.85])
        actions = policy.prepare_action(processed)
        losses = model.forward(images, img_masks, tokens, masks, actions, loss_noise, loss_time)
        refs["loss.noise"] = loss_noise
        refs["loss.time"] = loss_time
        refs["loss.elements"] = losses  # (B, T, max_action_dim)
        refs["loss.lerobot"] = losses[:, :, :ACTION_DIM].mean()  # PI05Policy.forward's reduction
        refs["loss.all_dims"] = losses.mean()  # openpi's reduction

    from safetensors.torch import save_file

    save_file(
        {k: v.detach().contiguous() for k, v in refs.items()},
        str(out / "reference.safetensors"),
        metadata={"tasks": json.dumps(TASKS), "cameras": json.dumps(CAMERAS)},
    )
    write_provenance(out, openpi, sys.argv)


OPENPI_VISION = {**VISION, "patch_size": 28}  # openpi always resizes to 224 px: 8 x 8 patches
OPENPI_CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
OPENPI_RAW_IMAGE = 56  # square, resized to 224 by openpi's preprocessing
OPENPI_MAX_TOKEN_LEN = 200  # Pi0Config(pi05=True).__post_init__


def import_openpi_pytorch(openpi: Path):
    """openpi's PyTorch model, tokenizer and normalisation from a checkout, without its JAX model
    stack: modules only the JAX model, FSQ/FAST tokenizers and GCS downloads use are stubbed (none is
    called on the paths run here), and ``openpi.models.gemma`` (flax) is replaced by a ``get_config``
    returning toy sizes, which is what it provides to the PyTorch model."""
    import types
    from unittest import mock

    sys.path.insert(0, str(openpi / "src"))
    sizes = {"gemma_2b": VLM, "gemma_300m": EXPERT}
    gemma = types.ModuleType("openpi.models.gemma")
    gemma.get_config = lambda variant: types.SimpleNamespace(**sizes[variant])
    sys.modules["openpi.models.gemma"] = gemma
    for name in (
        "orbax",
        "orbax.checkpoint",
        "openpi.models.utils",
        "openpi.models.utils.fsq_tokenizer",
        "openpi.shared.download",
        "openpi_client",
        "openpi_client.image_tools",
        "flax",
        "flax.traverse_util",  # used by Normalize.__call__ only
    ):
        sys.modules[name] = mock.MagicMock(name=name)
    import openpi.shared  # noqa: F401  (the real package, parent of the stubbed download module)
    from openpi.models import tokenizer
    from openpi.models_pytorch import gemma_pytorch, pi0_pytorch
    from openpi.shared import normalize

    patch_hf_sizes(gemma_pytorch, OPENPI_VISION)
    from openpi import transforms

    return pi0_pytorch, tokenizer, normalize, transforms


def make_openpi(out: Path, openpi: Path, tokenizer_dir: Path) -> None:
    """openpi's PyTorch pi05 (``PI0Pytorch`` with ``pi05=True``) saved in the layout of openpi's
    ``examples/convert_jax_model_to_pytorch.py`` / ``scripts/train_pytorch.py``: ``model.safetensors``
    by ``safetensors.torch.save_model`` (no ``model.`` prefix), the converter's ``config.json`` and
    ``assets/<asset_id>/norm_stats.json`` by ``openpi.shared.normalize.save``."""
    import types

    import numpy as np
    from safetensors.torch import save_file, save_model
    from transformers import AutoTokenizer

    pi0_pytorch, tokenizer_mod, normalize, transforms = import_openpi_pytorch(openpi)
    out.mkdir(parents=True, exist_ok=True)
    # Pi0Config(pi05=True, action_horizon=CHUNK) fields PI0Pytorch reads (pi0_config.py imports flax).
    config = types.SimpleNamespace(
        pi05=True,
        action_dim=32,
        action_horizon=CHUNK,
        max_token_len=OPENPI_MAX_TOKEN_LEN,
        paligemma_variant="gemma_2b",
        action_expert_variant="gemma_300m",
        dtype="float32",
        pytorch_compile_mode=None,
    )
    torch.manual_seed(SEED)
    model = pi0_pytorch.PI0Pytorch(config)
    randomize(model, torch.Generator().manual_seed(SEED + 10))
    model.eval()
    save_model(model, str(out / "model.safetensors"))
    # examples/convert_jax_model_to_pytorch.py writes this config.json
    (out / "config.json").write_text(
        json.dumps(
            {
                "action_dim": config.action_dim,
                "action_horizon": config.action_horizon,
                "paligemma_variant": config.paligemma_variant,
                "action_expert_variant": config.action_expert_variant,
                "precision": "float32",
            },
            indent=2,
        )
    )
    stats = statistics()
    norm_stats = {
        "state": normalize.NormStats(
            mean=stats["observation.state"]["mean"].numpy(),
            std=stats["observation.state"]["std"].numpy(),
            q01=stats["observation.state"]["q01"].numpy(),
            q99=stats["observation.state"]["q99"].numpy(),
        ),
        "actions": normalize.NormStats(
            mean=stats["action"]["mean"].numpy(),
            std=stats["action"]["std"].numpy(),
            q01=stats["action"]["q01"].numpy(),
            q99=stats["action"]["q99"].numpy(),
        ),
    }
    normalize.save(out / "assets" / "toy_robot", norm_stats)

    # The raw batch through openpi's own Normalize transform (quantiles, as pi05 configs use).
    raw = raw_batch(stats)
    g = torch.Generator().manual_seed(SEED + 5)
    images = {
        key: torch.rand(2, 3, OPENPI_RAW_IMAGE, OPENPI_RAW_IMAGE, generator=g)
        for key in OPENPI_CAMERAS
    }
    image_masks = {key: torch.tensor([True, True]) for key in OPENPI_CAMERAS}
    image_masks["right_wrist_0_rgb"] = torch.tensor([True, False])  # a missing camera in row 1
    # Normalize's per-key method (its __call__ walks the dict with flax.traverse_util, not installed).
    norm = transforms.Normalize(norm_stats, use_quantiles=True)
    state = norm._normalize_quantile(raw["observation.state"].numpy(), norm_stats["state"])
    actions = norm._normalize_quantile(raw["action"].numpy(), norm_stats["actions"])

    # openpi's PaligemmaTokenizer.tokenize (prompt format, state bins, padding), with the byte-level
    # stand-in in place of the sentencepiece model it downloads from GCS.
    hf = AutoTokenizer.from_pretrained(str(tokenizer_dir))

    class SentencePieceLike:
        def encode(self, text: str, add_bos: bool = False) -> list[int]:
            ids = hf(text, add_special_tokens=False)["input_ids"]
            return [hf.bos_token_id, *ids] if add_bos else ids

    tok = object.__new__(tokenizer_mod.PaligemmaTokenizer)
    tok._max_len = OPENPI_MAX_TOKEN_LEN
    tok._tokenizer = SentencePieceLike()
    tokenized = [tok.tokenize(task, s) for task, s in zip(TASKS, state, strict=True)]
    tokens = torch.from_numpy(np.stack([t for t, _ in tokenized])).long()
    token_mask = torch.from_numpy(np.stack([m for _, m in tokenized])).bool()

    def observation(state_t: torch.Tensor):
        # openpi Observation.from_dict maps float images to [-1, 1] as x * 2 - 1 (uint8 / 255 first).
        return types.SimpleNamespace(
            images={k: v * 2 - 1 for k, v in images.items()},
            image_masks=image_masks,
            state=state_t,
            tokenized_prompt=tokens,
            tokenized_prompt_mask=token_mask,
            token_ar_mask=None,
            token_loss_mask=None,
        )

    refs: dict[str, torch.Tensor] = {
        f"input.image.{i}": images[k] for i, k in enumerate(OPENPI_CAMERAS)
    }
    refs["input.image_mask"] = torch.stack([image_masks[k] for k in OPENPI_CAMERAS], dim=1)
    refs["input.state"] = raw["observation.state"]
    refs["input.actions"] = raw["action"]
    refs["normalized.state"] = torch.from_numpy(state).float()
    refs["normalized.actions"] = torch.from_numpy(actions).float()
    refs["tokens"], refs["token_mask"] = tokens, token_mask
    state_padded = torch.nn.functional.pad(refs["normalized.state"], (0, 24))  # PadStatesAndActions
    obs = observation(state_padded)
    with torch.no_grad():
        imgs, img_masks, lang_tokens, lang_masks, _ = model._preprocess_observation(
            obs, train=False
        )
        refs["image_features"] = torch.stack(
            [model.paligemma_with_expert.embed_image(img) for img in imgs], dim=1
        )
        prefix, _, _ = model.embed_prefix(imgs, img_masks, lang_tokens, lang_masks)
        refs["hidden.0"] = prefix[:, :, :8]  # the first 8 channels keep the file small
        noise = torch.randn(2, CHUNK, 32, generator=torch.Generator().manual_seed(3))
        refs["sample.noise"] = noise
        hidden: dict[int, torch.Tensor] = {}
        layers = model.paligemma_with_expert.paligemma.language_model.layers

        def keep(index: int):
            def hook(_module, _args, output) -> None:  # returns None: the output is unchanged
                value = output[0] if isinstance(output, tuple) else output
                hidden.setdefault(index, value[:, :, :8])

            return hook

        handles = [layer.register_forward_hook(keep(i + 1)) for i, layer in enumerate(layers)]
        refs["sample.actions"] = model.sample_actions("cpu", obs, noise=noise.clone(), num_steps=10)
        for handle in handles:
            handle.remove()
        for index, value in hidden.items():
            refs[f"hidden.{index}"] = value
        loss_noise = torch.randn(2, CHUNK, 32, generator=torch.Generator().manual_seed(4))
        loss_time = torch.tensor([0.3, 0.85])
        padded_actions = torch.nn.functional.pad(refs["normalized.actions"], (0, 32 - ACTION_DIM))
        # PI0Pytorch.forward always preprocesses with train=True (random crops, rotation, colour
        # jitter); the loss reference is taken without that augmentation, which capvector does not
        # reproduce (its own augmentation is in capvector.data.transforms).
        model._preprocess_observation = lambda o, train=True, _f=model._preprocess_observation: _f(
            o, train=False
        )
        losses = model.forward(obs, padded_actions, noise=loss_noise, time=loss_time)
        refs["loss.noise"], refs["loss.time"] = loss_noise, loss_time
        refs["loss.elements"] = losses
        refs["loss.openpi"] = losses.mean()  # pi0.py compute_loss / train_pytorch.py: all 32 dims
    save_file(
        {k: v.detach().contiguous() for k, v in refs.items()},
        str(out / "reference.safetensors"),
        metadata={"tasks": json.dumps(TASKS), "cameras": json.dumps(OPENPI_CAMERAS)},
    )


def write_provenance(out: Path, openpi: Path, argv: list[str]) -> None:
    def version(name: str) -> str:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "not installed"

    def commit(path: Path) -> str:
        try:
            return subprocess.run(
                ["git", "-C", str(path), "rev-parse", "HEAD"],
                capture_output=True,
                text=True,
                check=True,
            ).stdout.strip()
        except (subprocess.CalledProcessError, FileNotFoundError):
            return (
                (path / "COMMIT").read_text().strip() if (path / "COMMIT").is_file() else "unknown"
            )

    lines = [
        "Pi0.5 parity fixture, variant `lerobot`: LeRobot's PyTorch pi05 policy at toy size.",
        "",
        "upstream: huggingface/lerobot, PyPI lerobot==" + version("lerobot"),
        "  src/lerobot/policies/pi05/{configuration_pi05,modeling_pi05,processor_pi05}.py",
        "transformers: " + version("transformers") + " with openpi's transformers_replace patch "
        f"applied (Physical-Intelligence/openpi {commit(openpi)}, "
        "src/openpi/models_pytorch/transformers_replace), as LeRobot 0.4.4 requires",
        f"torch {torch.__version__}, safetensors {version('safetensors')}, numpy {version('numpy')}, "
        f"tokenizers {version('tokenizers')}, python {sys.version.split()[0]}",
        "",
        "command (run in the scratch venv, from the capvector repository root):",
        "  python " + " ".join(argv),
        "",
        "deviations from a real checkpoint:",
        "- toy sizes patched in by the script (get_gemma_config, the PaliGemma/Gemma HF configs):",
        f"  VLM {VLM}, expert {EXPERT}, SigLIP {VISION}, vocab {VOCAB}, image {IMAGE} px;",
        f"  chunk_size {CHUNK}, action dim {ACTION_DIM}, state dim {STATE_DIM}, "
        f"num_inference_steps {STEPS}, 2 cameras;",
        "- every parameter random from seed 0 (adaRMS weights too, which LeRobot zero-inits);",
        "- tokenizer/ is a byte-level stand-in for google/paligemma-3b-pt-224 (the hub is not",
        "  reachable); LeRobot's TokenizerProcessorStep loaded it in place of that name;",
        "- CPU, float32, eager attention (LeRobot's own path on CPU);",
        "- torch " + torch.__version__ + " although lerobot 0.4.4 pins torch<2.11 (the machine's",
        "  pip only installs this local build); lerobot installed with --no-deps plus the",
        "  dependencies its pi05 import needs.",
        "- raw images are square 48 px: LeRobot 0.4.4 pads non-square images with -1 *before* its",
        "  [0,1] -> [-1,1] map (-3 in model space); padding is left out of the parity batch.",
        "",
        "LeRobot 0.4.4 behaviour the parity test reproduces through an override, not by default:",
        "- the state is zero-padded to max_state_dim (32) before it is discretised into the prompt",
        "  (24 extra '128' tokens); openpi and LeRobot since f0d2b37 use the unpadded state, which is",
        "  capvector's default; load with overrides={'prompt_state_dim': 32} for this folder.",
        "- the state's first value normalises below -1 (bin -1 in the prompt), some actions beyond",
        "  [-1, 1] (LeRobot's QUANTILES normalisation does not clip).",
        "",
        "reference.safetensors: inputs (input.*), normalised state/actions, tokens, SigLIP and",
        "projected image features, prefix hidden states hidden.0..2 (embeddings, layer outputs),",
        "actions sampled from sample.noise, their postprocessed raw values, the training loss",
        "elements at loss.noise / loss.time; metadata: tasks, cameras.",
    ]
    (out / "PROVENANCE").write_text("\n".join(lines) + "\n")


def write_openpi_provenance(out: Path, openpi: Path, argv: list[str]) -> None:
    lines = [
        "Pi0.5 parity fixture, variant `openpi`: openpi's PyTorch pi05 model at toy size.",
        "",
        f"upstream: Physical-Intelligence/openpi {_commit(openpi)}",
        "  src/openpi/models_pytorch/{pi0_pytorch,gemma_pytorch,preprocessing_pytorch}.py,",
        "  src/openpi/models/tokenizer.py (PaligemmaTokenizer.tokenize), src/openpi/transforms.py",
        "  (Normalize, quantiles), src/openpi/shared/normalize.py (NormStats, save)",
        f"transformers {_version('transformers')} with openpi's transformers_replace patch applied;",
        f"torch {torch.__version__}, jax {_version('jax')} (CPU; imported by openpi.shared.image_tools),",
        f"numpy {_version('numpy')}, python {sys.version.split()[0]}",
        "",
        "command (run in the scratch venv, from the capvector repository root):",
        "  python " + " ".join(argv),
        "",
        "layout: model.safetensors written by safetensors.torch.save_model (no `model.` prefix) and",
        "config.json as examples/convert_jax_model_to_pytorch.py writes them; norm stats in",
        "assets/toy_robot/norm_stats.json by openpi.shared.normalize.save (train_pytorch.py's place).",
        "",
        "deviations:",
        f"- toy sizes: VLM {VLM}, expert {EXPERT}, SigLIP {OPENPI_VISION}, vocab {VOCAB};",
        "  openpi.models.gemma (flax) is replaced by a get_config returning these; the HF configs",
        "  gemma_pytorch builds are pinned to them as for the lerobot variant;",
        "- Pi0Config (flax import) replaced by a namespace with the fields PI0Pytorch reads:",
        f"  pi05=True, action_dim 32, action_horizon {CHUNK}, max_token_len {OPENPI_MAX_TOKEN_LEN}, float32;",
        "- modules used only by the JAX model, FSQ/FAST tokenizers and GCS downloads are stubbed",
        "  (orbax, flax, fsq_tokenizer, download, openpi_client): none runs on these paths;",
        "- PaligemmaTokenizer.tokenize runs with the lerobot variant's byte-level stand-in in place",
        "  of the sentencepiece model (paligemma_tokenizer.model is on GCS, unreachable here);",
        "- every parameter random from seed 10; CPU, float32, eager attention;",
        "- 3 cameras (openpi's IMAGE_KEYS), 56 px square raw images resized to 224 by openpi;",
        "  right_wrist masked in row 1; state 8-d, tokenized unpadded, then padded to 32;",
        "- the training loss is taken with _preprocess_observation(train=False): PI0Pytorch.forward",
        "  augments images at random (crop, rotation, colour jitter), which capvector does not copy.",
        "",
        "reference.safetensors: inputs, normalised state/actions (openpi Normalize), tokens, image",
        "features, prefix hidden states hidden.0..2 (first 8 channels), actions sampled in 10 steps",
        "from sample.noise, loss elements at loss.noise / loss.time and their mean over 32 dims.",
    ]
    (out / "PROVENANCE").write_text("\n".join(lines) + "\n")


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def _commit(path: Path) -> str:
    try:
        return subprocess.run(
            ["git", "-C", str(path), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (subprocess.CalledProcessError, FileNotFoundError):
        return (path / "COMMIT").read_text().strip() if (path / "COMMIT").is_file() else "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--openpi", type=Path, required=True, help="openpi checkout (its patch is installed)"
    )
    parser.add_argument("--out", type=Path, default=Path("tests/fixtures/upstream/pi05"))
    args = parser.parse_args()
    make_lerobot(args.out / "lerobot", args.openpi)
    print(f"wrote {args.out / 'lerobot'}")
    make_openpi(args.out / "openpi", args.openpi, args.out / "lerobot" / "tokenizer")
    write_openpi_provenance(args.out / "openpi", args.openpi, sys.argv)
    print(f"wrote {args.out / 'openpi'}")


if __name__ == "__main__":
    main()
