"""Reference fixtures for capvector's StarVLA importer, produced by StarVLA's own code.

Run in a scratch environment with StarVLA's pinned stack (transformers 4.57.0; see the PROVENANCE
files this writes), NOT in capvector's environment, and point it at a StarVLA checkout::

    python tools/starvla/make_upstream_fixtures.py --starvla /path/to/starVLA \
        --out tests/fixtures/upstream/starvla [--variants qwen2.5-vl-oft ...]

Per variant it builds a tiny Qwen-VL folder (config, random weights from a fixed seed, a small
byte-level BPE tokenizer with Qwen's special tokens, pre-tokenizer and chat template, the Qwen
processor's config), builds StarVLA's framework on it through StarVLA's ``build_framework`` path
(``FRAMEWORK_REGISTRY``), and writes what StarVLA's trainer writes for a run::

    <variant>/run/checkpoints/steps_1_pytorch_model.pt   (``VLATrainer._save_checkpoint``, pt format)
    <variant>/run/config.yaml                            (``save_accessed_config``, accessed keys)
    <variant>/run/dataset_statistics.json                (gr00t_lerobot's statistics layout)

plus ``reference.safetensors``: the fixed batch's inputs (images as uint8, actions, states),
StarVLA's token ids, pixel values, hidden states of a few VLM layers, the framework's training loss
on that batch in eval mode with its recorded noise and flow times, and its predicted actions with
the recorded initial noise. No StarVLA code is copied; it is imported from ``--starvla``.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

SEED = 0
IMAGE_SIZE = 56  # a multiple of 28: qwen_vl_utils' resize leaves it alone
NUM_CAMERAS = 2
ACTION_DIM = 7
STATE_DIM = 7
CHUNK = 4
INSTRUCTIONS = ["pick up the red block", "open the top drawer please"]
EMOJI = "\U0001f50d"  # QwenOFT's query placeholder: the tiny vocabulary makes it one token
QWEN_SPECIALS = [
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<|vision_start|>",
    "<|vision_end|>",
    "<|image_pad|>",
    "<|video_pad|>",
]
# Qwen2's pre-tokenizer split pattern (tokenizer.json of Qwen/Qwen2.5-VL-3B-Instruct).
QWEN_PRETOKENIZE = (
    r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*"
    r"|\s*[\r\n]+|\s+(?!\S)|\s+"
)
# Qwen2.5-VL's chat template (image and text parts).
CHAT_TEMPLATE = (
    "{% set image_count = namespace(value=0) %}{% for message in messages %}"
    "{% if loop.first and message['role'] != 'system' %}<|im_start|>system\n"
    "You are a helpful assistant.<|im_end|>\n{% endif %}<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}<|im_end|>\n"
    "{% else %}{% for content in message['content'] %}"
    "{% if content['type'] == 'image' or 'image' in content or 'image_url' in content %}"
    "{% set image_count.value = image_count.value + 1 %}"
    "{% if add_vision_id %}Picture {{ image_count.value }}: {% endif %}"
    "<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif 'text' in content %}{{ content['text'] }}{% endif %}{% endfor %}<|im_end|>\n"
    "{% endif %}{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)

TEXT = {
    "hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2,
    "num_attention_heads": 2, "num_key_value_heads": 1, "max_position_embeddings": 2048,
    "rms_norm_eps": 1e-6,
}  # fmt: skip
QWEN = {
    "qwen2.5-vl": {
        "folder": "Qwen2.5-VL-tiny",  # StarVLA picks its wrapper by this substring
        "text": {**TEXT, "rope_theta": 1e6, "rope_scaling": {"type": "mrope", "mrope_section": [2, 3, 3]}},
        "vision": {
            "depth": 2, "hidden_size": 16, "intermediate_size": 32, "num_heads": 1,
            "out_hidden_size": 32, "patch_size": 14, "spatial_merge_size": 2,
            "temporal_patch_size": 2, "window_size": 56, "fullatt_block_indexes": [1],
            "hidden_act": "silu", "tokens_per_second": 2,
        },
        # Qwen2.5-VL's processor defaults: 56*56 .. 28*28*1280 pixels, CLIP statistics.
        "min_pixels": 3136, "max_pixels": 1003520,
        "mean": [0.48145466, 0.4578275, 0.40821073], "std": [0.26862954, 0.26130258, 0.27577711],
    },
    "qwen3-vl": {
        "folder": "Qwen3-VL-tiny",
        "text": {
            **TEXT, "head_dim": 16, "rope_theta": 5e6,
            "rope_scaling": {"rope_type": "default", "mrope_section": [4, 2, 2], "mrope_interleaved": True},
        },
        "vision": {
            "depth": 2, "hidden_size": 16, "intermediate_size": 32, "num_heads": 1,
            "out_hidden_size": 32, "patch_size": 16, "spatial_merge_size": 2,
            "temporal_patch_size": 2, "num_position_embeddings": 64,
            "deepstack_visual_indexes": [0], "hidden_act": "gelu_pytorch_tanh",
        },
        # Qwen3-VL's processor upsamples small images: min_pixels = 65536 (256 x 256) for the 4B
        # model, so its 224-px cameras grow; here 96 x 96 is the floor, so 56-px cameras grow.
        "min_pixels": 9216, "max_pixels": 16777216,
        "mean": [0.5, 0.5, 0.5], "std": [0.5, 0.5, 0.5],
    },
}  # fmt: skip

# variant -> (qwen version, framework name, framework/trainer config, uses state)
FLOW_TINY = {
    "action_model_type": "DiT-tiny",
    "hidden_size": 16,
    "action_hidden_dim": 16,
    "add_pos_embed": True,
    "max_seq_len": 16,
    "noise_beta_alpha": 1.5,
    "noise_beta_beta": 1.0,
    "noise_s": 0.999,
    "num_timestep_buckets": 1000,
    "num_inference_timesteps": 4,
    "num_target_vision_tokens": 4,
}
# Upstream's DiTConfig table has only DiT-B (768) and DiT-L (1536); a tiny size is registered as one
# more entry of that table (no upstream code changes), so fixtures stay a few hundred kB.
DIT_TINY = {"input_embedding_dim": 16, "attention_head_dim": 8, "num_attention_heads": 2}


def variants() -> dict[str, dict]:
    out = {}
    for version in QWEN:
        out[f"{version}-oft"] = {
            "qwen": version,
            "framework": "QwenOFT",
            "module": "QwenOFT",
            "action_model": {"action_model_type": "MLP"},
            "state": False,
        }
        for state in (False, True):
            out[f"{version}-gr00t" + ("-state" if state else "")] = {
                "qwen": version,
                "framework": "QwenGR00T",
                "module": "QwenGR00T",
                "action_model": {
                    **FLOW_TINY,
                    "repeated_diffusion_steps": 3,
                    "state_dim": STATE_DIM if state else None,
                    "diffusion_model_cfg": {
                        **DIT_TINY,
                        "dropout": 0.2,
                        "final_dropout": True,
                        "interleave_self_attention": True,
                        "norm_type": "ada_norm",
                        "num_layers": 2,
                        "output_dim": 16,
                        "positional_embeddings": None,
                    },
                },
                "state": state,
            }
        for interleave in (False, True):
            out[f"{version}-pi-v3" + ("-interleave" if interleave else "")] = {
                "qwen": version,
                "framework": "QwenPI_v3",
                "module": "QwenPI_v3",
                "action_model": {
                    **FLOW_TINY,
                    "action_model_type": "LayerwiseFM",
                    "state_dim": STATE_DIM,
                    "diffusion_model_cfg": {
                        "action_dit_hidden_dim": 16,
                        "attention_head_dim": 8,
                        "dropout": 0.2,
                        "final_dropout": True,
                        "interleave_self_attention": interleave,
                        "norm_type": "ada_norm",
                        "positional_embeddings": None,
                    },
                },
                "trainer": {"repeated_diffusion_steps": 3},
                "state": True,  # QwenPI_v3 writes the state into the prompt as 256 bins
            }
    return out


# -- the tiny Qwen folder ---------------------------------------------------------------------------


def qwen_tokenizer():
    """Byte-level BPE with Qwen's pre-tokenizer, merges making the emoji one token, Qwen's specials."""
    from tokenizers import Regex, Tokenizer, decoders, models, pre_tokenizers
    from transformers import Qwen2TokenizerFast

    byte_chars = pre_tokenizers.ByteLevel.alphabet()
    encode = {b: c for b, c in zip(range(256), _bytes_to_unicode(), strict=True)}
    assert set(encode.values()) == set(byte_chars)
    vocab = {encode[b]: b for b in range(256)}
    emoji = [encode[b] for b in EMOJI.encode()]
    merges = []
    merged = emoji[0]
    for piece in emoji[1:]:
        merges.append((merged, piece))
        merged += piece
        vocab[merged] = len(vocab)
    # Qwen's vocabulary has "<a" (HTML): with it, splitting the query tokens out of the text
    # would change how "<action>" after them is tokenised (see the parity tests).
    merges.append(("<", "a"))
    vocab["<a"] = len(vocab)
    backend = Tokenizer(models.BPE(vocab=vocab, merges=merges))
    backend.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(QWEN_PRETOKENIZE), behavior="isolated"),
            pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False),
        ]
    )
    backend.decoder = decoders.ByteLevel()
    tok = Qwen2TokenizerFast(
        tokenizer_object=backend,
        model_max_length=4096,
        unk_token=None,
        bos_token=None,
        eos_token="<|im_end|>",
        pad_token="<|endoftext|>",
    )
    tok.add_special_tokens({"additional_special_tokens": QWEN_SPECIALS})
    tok.chat_template = CHAT_TEMPLATE
    return tok


def _bytes_to_unicode() -> list[str]:
    """GPT-2's byte -> printable character table, in byte order."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1))
    bs += list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    table = dict(zip(bs, cs, strict=True))
    return [chr(table[b]) for b in range(256)]


def write_qwen_folder(version: str, root: Path) -> Path:
    import transformers

    spec = QWEN[version]
    folder = root / spec["folder"]
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    tok = qwen_tokenizer()
    ids = {t: tok.convert_tokens_to_ids(t) for t in QWEN_SPECIALS}
    vocab = len(tok) + (-len(tok)) % 16
    common = {
        "image_token_id": ids["<|image_pad|>"],
        "video_token_id": ids["<|video_pad|>"],
        "vision_start_token_id": ids["<|vision_start|>"],
        "vision_end_token_id": ids["<|vision_end|>"],
        "tie_word_embeddings": True,
    }
    text = {
        **spec["text"],
        "vocab_size": vocab,
        "tie_word_embeddings": True,
        "bos_token_id": None,
        "eos_token_id": ids["<|im_end|>"],
        "pad_token_id": ids["<|endoftext|>"],
    }
    if version == "qwen2.5-vl":
        config = transformers.Qwen2_5_VLConfig(
            text_config=text, vision_config=spec["vision"], torch_dtype="float32", **common
        )
        model_class = transformers.Qwen2_5_VLForConditionalGeneration
        processor_class = transformers.Qwen2_5_VLProcessor
        image_processor = transformers.Qwen2VLImageProcessor(
            min_pixels=spec["min_pixels"], max_pixels=spec["max_pixels"], patch_size=14,
            merge_size=2, temporal_patch_size=2, image_mean=spec["mean"], image_std=spec["std"],
        )  # fmt: skip
    else:
        config = transformers.Qwen3VLConfig(
            text_config=text, vision_config=spec["vision"], torch_dtype="float32", **common
        )
        model_class = transformers.Qwen3VLForConditionalGeneration
        processor_class = transformers.Qwen3VLProcessor
        image_processor = transformers.Qwen2VLImageProcessorFast(
            size={"shortest_edge": spec["min_pixels"], "longest_edge": spec["max_pixels"]},
            patch_size=16, merge_size=2, temporal_patch_size=2, image_mean=spec["mean"],
            image_std=spec["std"],
        )  # fmt: skip
    torch.manual_seed(SEED)
    model = model_class(config).float()
    model.save_pretrained(str(folder), safe_serialization=True)
    if version == "qwen3-vl":
        video = transformers.Qwen3VLVideoProcessor(patch_size=16, merge_size=2)
    else:
        video = transformers.Qwen2VLVideoProcessor(patch_size=14, merge_size=2)
    processor = processor_class(
        image_processor=image_processor,
        tokenizer=tok,
        video_processor=video,
        chat_template=CHAT_TEMPLATE,
    )
    processor.save_pretrained(str(folder))
    return folder


# -- one variant ------------------------------------------------------------------------------------


def fixed_batch(spec: dict) -> tuple[list[dict], dict[str, np.ndarray]]:
    from PIL import Image

    rng = np.random.default_rng(SEED)
    images = rng.integers(0, 256, (len(INSTRUCTIONS), NUM_CAMERAS, IMAGE_SIZE, IMAGE_SIZE, 3))
    images = images.astype(np.uint8)
    actions = rng.uniform(-1, 1, (len(INSTRUCTIONS), CHUNK, ACTION_DIM)).astype(np.float32)
    # Includes values outside [-1, 1]: StarVLA bins them as np.digitize does (-1 below the range).
    states = rng.uniform(-1.2, 1.2, (len(INSTRUCTIONS), 1, STATE_DIM)).astype(np.float32)
    examples = []
    for i, lang in enumerate(INSTRUCTIONS):
        example = {
            "image": [Image.fromarray(images[i, c]) for c in range(NUM_CAMERAS)],
            "lang": lang,
            "action": actions[i],
        }
        if spec["state"]:
            example["state"] = states[i]
        examples.append(example)
    arrays = {"images": images, "actions": actions}
    if spec["state"]:
        arrays["states"] = states[:, 0]
    return examples, arrays


def base_config(spec: dict, qwen_folder: Path, run_dir: Path):
    from omegaconf import OmegaConf

    cfg = {
        "run_id": "tiny",
        "output_dir": str(run_dir),
        "seed": SEED,
        "framework": {
            "name": spec["framework"],
            "qwenvl": {"base_vlm": str(qwen_folder), "attn_implementation": "sdpa"},
            "action_model": {
                "action_dim": ACTION_DIM,
                "action_horizon": CHUNK,
                **spec["action_model"],
            },
        },
        "datasets": {
            "vla_data": {
                "dataset_py": "lerobot_datasets",
                "data_mix": "tiny",
                "obs_image_size": [IMAGE_SIZE, IMAGE_SIZE],
            }
        },
        "trainer": {"save_format": "pt", **spec.get("trainer", {})},
    }
    return OmegaConf.create(cfg)


def record_randn():
    """Patch torch.randn to record what it returns (the heads draw noise with it)."""
    drawn: list[torch.Tensor] = []
    original = torch.randn

    def randn(*args, **kwargs):
        out = original(*args, **kwargs)
        drawn.append(out.detach().clone())
        return out

    return drawn, original, randn


def run_variant(name: str, spec: dict, starvla: Path, out: Path, qwen_folder: Path) -> None:
    from safetensors.torch import save_file
    from starVLA.model.framework.share_tools import apply_config_compat
    from starVLA.model.tools import FRAMEWORK_REGISTRY
    from starVLA.training.trainer_utils.config_tracker import wrap_config

    variant_dir = out / name
    if variant_dir.exists():
        shutil.rmtree(variant_dir)
    run_dir = variant_dir / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    cfg = base_config(spec, qwen_folder, run_dir)
    cfg = apply_config_compat(cfg)  # as train_starvla.py's __main__
    cfg = wrap_config(cfg)  # as train_starvla.main: config.yaml holds the accessed keys
    __import__(f"starVLA.model.framework.VLM4A.{spec['module']}")
    torch.manual_seed(SEED)
    # base_framework.build_framework's lookup (its module auto-import needs every optional
    # dependency of every framework, so the one module is imported above instead).
    model = FRAMEWORK_REGISTRY[cfg.framework.name](cfg)
    model = model.float()
    # A few weights zero at init (GR00T's future tokens etc. are already random); perturb every
    # parameter so no term of the comparison is trivially zero.
    with torch.no_grad():
        gen = torch.Generator().manual_seed(SEED + 1)
        for p in model.parameters():
            p.add_(0.02 * torch.randn(p.shape, generator=gen))
    model.eval()  # no dropout: the references are deterministic given the recorded noise

    examples, arrays = fixed_batch(spec)
    refs: dict[str, torch.Tensor] = {k: torch.from_numpy(v) for k, v in arrays.items()}

    # Training loss on the batch (eval mode), recording the noise and flow times drawn.
    drawn, original, randn = record_randn()
    times: list[torch.Tensor] = []
    head = model.action_model
    if hasattr(head, "sample_time"):
        sample_time = head.sample_time

        def recorded_time(*args, **kwargs):
            t = sample_time(*args, **kwargs)
            times.append(t.detach().clone())
            return t

        head.sample_time = recorded_time
    # The framework's own prompt (state bins, OFT suffix, chat template) as it builds it.
    built: list = []
    build = model.qwen_vl_interface.build_qwenvl_inputs

    def recorded_build(*args, **kwargs):
        built.append(build(*args, **kwargs))
        return built[-1]

    model.qwen_vl_interface.build_qwenvl_inputs = recorded_build
    torch.manual_seed(SEED + 2)
    torch.randn = randn
    try:
        with torch.no_grad():
            loss = model(examples)["action_loss"]
    finally:
        torch.randn = original
        del model.qwen_vl_interface.build_qwenvl_inputs
        if hasattr(head, "sample_time"):
            del head.sample_time
    refs["loss"] = loss.detach().reshape(1)
    if times:
        refs["loss_noise"] = drawn[-1]
        refs["loss_time"] = times[-1]

    # The VLM's hidden states on those inputs, through StarVLA's wrapper (what its heads read).
    inputs = built[-1]
    with torch.no_grad():
        outputs = model.qwen_vl_interface(**inputs, output_hidden_states=True, return_dict=True)
    hidden = outputs.hidden_states
    refs["input_ids"] = inputs["input_ids"]
    refs["attention_mask"] = inputs["attention_mask"]
    refs["image_grid_thw"] = inputs["image_grid_thw"]
    refs["pixel_values_sum"] = inputs["pixel_values"].double().sum().reshape(1)
    refs["pixel_values_abs_sum"] = inputs["pixel_values"].double().abs().sum().reshape(1)
    with torch.no_grad():
        vision = model.qwen_vl_interface.model.model.get_image_features(
            inputs["pixel_values"], inputs["image_grid_thw"]
        )
    if isinstance(vision[0], (tuple, list)):  # Qwen3-VL: (per-image embeds, deepstack features)
        vision = vision[0]
    refs["vision_features"] = torch.cat(list(vision), dim=0)  # per-image embeds, concatenated
    for layer in sorted({0, 1, len(hidden) - 1}):
        refs[f"hidden_states.{layer}"] = hidden[layer]

    # Predicted actions, recording the initial noise of the flow heads.
    drawn, original, randn = record_randn()
    torch.manual_seed(SEED + 3)
    torch.randn = randn
    try:
        predicted = model.predict_action(examples=examples)["normalized_actions"]
    finally:
        torch.randn = original
    refs["actions_pred"] = torch.from_numpy(np.asarray(predicted))
    if drawn:
        refs["predict_noise"] = drawn[-1]

    # What StarVLA's trainer writes (VLATrainer._save_checkpoint, pt format; config.yaml from the
    # access tracker; dataset_statistics.json in gr00t_lerobot's layout).
    state_dict = model.state_dict()
    torch.save(state_dict, run_dir / "checkpoints" / "steps_1_pytorch_model.pt")
    cfg.save_accessed_config(run_dir / "config.yaml", use_original_values=False)
    write_statistics(run_dir / "dataset_statistics.json", spec)
    save_file(
        {k: v.detach().contiguous() for k, v in refs.items()},
        str(variant_dir / "reference.safetensors"),
        metadata={"variant": name},
    )
    print(name, "loss", float(loss), "actions", tuple(refs["actions_pred"].shape))


def write_statistics(path: Path, spec: dict) -> None:
    """dataset_statistics.json in gr00t_lerobot's ``save_dataset_statistics`` layout: per embodiment
    tag, action/state statistics concatenated over the modality keys in key order (what its
    ``combine_modality_stats`` does; importing that module needs pytorch3d, so the concatenation is
    done here), the action mask False for binary-normalised keys (LIBERO's gripper)."""
    rng = np.random.default_rng(SEED + 4)
    keys = ["x", "y", "z", "roll", "pitch", "yaw", "gripper"]

    def combined() -> dict:
        out: dict = {name: [] for name in ("mean", "std", "max", "min", "q01", "q99")}
        for _key in keys:
            x = rng.normal(size=(200, 1)) * rng.uniform(0.1, 2.0) + rng.normal()
            out["mean"] += x.mean(0).tolist()
            out["std"] += x.std(0).tolist()
            out["max"] += x.max(0).tolist()
            out["min"] += x.min(0).tolist()
            out["q01"] += np.quantile(x, 0.01, axis=0).tolist()
            out["q99"] += np.quantile(x, 0.99, axis=0).tolist()
        return out

    entry: dict = {"action": {**combined(), "mask": [True] * 6 + [False]}}
    if spec["state"]:
        entry["state"] = combined()
    entry.update({"num_transitions": 200, "num_trajectories": 4})
    path.write_text(json.dumps({"libero_franka": entry}, indent=2, ensure_ascii=False))


def provenance(out: Path, starvla: Path, names: list[str], argv: list[str]) -> None:
    import subprocess
    from importlib.metadata import version

    import accelerate
    import diffusers
    import PIL
    import qwen_vl_utils  # noqa: F401  (imported by StarVLA's wrappers; version from metadata)
    import tokenizers
    import torchvision
    import transformers

    commit = (
        subprocess.run(
            ["git", "-C", str(starvla), "rev-parse", "HEAD"], capture_output=True, text=True
        ).stdout.strip()
        or (starvla / "COMMIT").read_text().strip()
    )
    text = f"""Upstream: https://github.com/starVLA/starVLA at commit {commit}
Generated by: tools/starvla/make_upstream_fixtures.py (this repository), importing StarVLA's code
from a checkout; no StarVLA code is stored here, only what it produced.
Command: python {" ".join(argv)}
Environment: Python {platform.python_version()}, torch {torch.__version__}, torchvision
{torchvision.__version__}, transformers {transformers.__version__} and accelerate
{accelerate.__version__} and numpy {np.__version__} (StarVLA's requirements.txt pins), diffusers
{diffusers.__version__}, qwen-vl-utils {version("qwen-vl-utils")}, tokenizers {tokenizers.__version__},
Pillow {PIL.__version__}; CPU only. The checkout is `git archive` of the commit above.
Qwen processors: Qwen2.5-VL's slow Qwen2VLImageProcessor and Qwen3-VL's Qwen2VLImageProcessorFast,
as the real checkpoints' preprocessor_config.json select.
Variants: {", ".join(names)}

Deviations from a real StarVLA run, all forced by size or the CPU:
- torch 2.14.1 / torchvision 0.29.1 instead of StarVLA's torchvision 0.21 pin (the only builds
  this machine's pip accepts); no CUDA, so StarVLA's bf16 autocast regions do not apply and
  everything runs in fp32; flash-attention is absent, so the wrappers fall back to sdpa
  (attn_implementation: sdpa is set in the config).
- The VLM is a tiny random Qwen-VL (32 wide, 2 layers) with a tiny byte-level BPE tokenizer
  (Qwen's special tokens, pre-tokenizer split pattern and chat template; merges only for the
  emoji query, so it is one token as in Qwen's vocabulary, and for "<a", a Qwen token). The
  folder keeps no weights file: the checkpoint holds every weight.
- Cameras are 56 px (StarVLA's loader gives 224): 56 is a multiple of qwen_vl_utils' factor 28,
  and Qwen3-VL's processor (min_pixels 9216 here) upsamples it to 96 px, as the real one
  (min_pixels 65536) upsamples 224 to 256.
- Upstream's DiT size table (GR00T_ActionHeader.DiTConfig) has DiT-B/DiT-L only; the script adds a
  'DiT-tiny' row (16 wide, 2 heads x 8) to that dict at run time. No upstream code is changed.
- Weights: the framework is built with torch.manual_seed({SEED}), then every parameter gets
  N(0, 0.02^2) added (seed {SEED + 1}) so that zero-initialised terms do not hide differences.
- References are computed in eval mode (dropout off). The training loss is StarVLA's forward()
  on the batch; the noise (torch.randn) and flow times (head.sample_time) it drew are recorded
  as loss_noise / loss_time; predict_action()'s initial noise as predict_noise.
- config.yaml is written by StarVLA's AccessTrackedConfig after one forward and one
  predict_action, as the trainer does at a checkpoint; dataset_statistics.json is built with
  random per-key statistics in gr00t_lerobot's layout (no dataset is read).
"""
    (out / "PROVENANCE").write_text(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--starvla", type=Path, required=True, help="a StarVLA checkout")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--variants", nargs="*", default=None)
    args = parser.parse_args()
    sys.path.insert(0, str(args.starvla.resolve()))
    # The tiny DiT row of upstream's size table (see PROVENANCE).
    from starVLA.model.modules.action_model import GR00T_ActionHeader

    GR00T_ActionHeader.DiTConfig["DiT-tiny"] = dict(DIT_TINY)

    table = variants()
    names = args.variants or list(table)
    unknown = sorted(set(names) - set(table))
    if unknown:
        raise SystemExit(f"unknown variants {unknown}; known: {sorted(table)}")
    args.out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    for version in sorted({table[n]["qwen"] for n in names}):
        qwen_root = args.out / "qwen" / version
        folder = write_qwen_folder(version, qwen_root)
        for name in [n for n in names if table[n]["qwen"] == version]:
            run_variant(name, table[name], args.starvla, args.out, folder)
        (folder / "model.safetensors").unlink()
    provenance(args.out, args.starvla, names, sys.argv)


if __name__ == "__main__":
    main()
