"""Write OpenVLA-OFT parity fixtures with the upstream code (moojink/openvla-oft).

Runs in a scratch environment with upstream's pins (timm==0.9.10, tokenizers==0.19.1,
peft==0.11.1, transformers from moojink/transformers-openvla-oft), never in capvector's own::

    PYTHONHASHSEED=0 python tools/openvla_oft/make_upstream_fixtures.py --upstream /path/to/openvla-oft \\
        --variant libero --out tests/fixtures/upstream/openvla_oft/libero
    PYTHONHASHSEED=0 python tools/openvla_oft/make_upstream_fixtures.py --upstream /path/to/openvla-oft \\
        --variant aloha --out tests/fixtures/upstream/openvla_oft/aloha_film

It imports upstream's own classes from the checkout and walks through what ``vla-scripts/finetune.py``
does at tiny size on CPU: build the VLA, save it as the "pretrained" base (bf16, as finetune.py loads
it), add LoRA (``all-linear``), wrap the vision backbone with FiLM (``aloha``), wrap every trained
module in DDP (gloo, one process), save ``action_head--N``, ``proprio_projector--N`` and
``vision_backbone--N`` the way ``save_training_checkpoint`` does, then merge the LoRA adapter into a
freshly loaded base and ``save_pretrained`` the merged model. The references are then computed from
the saved files, loaded the way ``experiments/robot/openvla_utils.py`` loads them, in fp32.

Nothing of upstream is copied: the script only calls it. What it changes is listed in PROVENANCE.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import torch

STEP = 5
SEED = 0
LORA_RANK = 4
INSTRUCTIONS = {
    # Different lengths: the training batch is right padded (no FiLM, so padding is upstream-exact).
    "libero": ["put the bowl on the plate", "open the top drawer and put the bowl inside"],
    # Same length: FiLM averages pad embeddings into the language embedding in a padded training
    # batch (film_vit_wrapper.py), so the FiLM batch is unpadded (see PROVENANCE).
    "aloha": ["fold the towel", "open the pouch"],
}
# Tiny timm ViTs built through upstream's own `timm.create_model(model_id, ...)` call: only the
# width and depth change, everything else is the registered model's.
TINY_VIT = {
    "vit_large_patch14_reg4_dinov2.lvd142m": dict(embed_dim=32, depth=3, num_heads=4),
    "vit_so400m_patch14_siglip_224": dict(embed_dim=48, depth=3, num_heads=4),
}
TINY_LLAMA = dict(
    vocab_size=32064,  # Llama-2's 32000 + <PAD>, padded to a multiple of 64 as OpenVLA's checkpoints
    hidden_size=16,
    intermediate_size=32,
    num_hidden_layers=3,
    num_attention_heads=2,
    num_key_value_heads=2,
    max_position_embeddings=2048,
    rms_norm_eps=1e-6,
    pad_token_id=32000,
)


def stub_package(name: str, path: Path | None = None, **attrs: object) -> types.ModuleType:
    """A package module whose __init__ is not run (upstream's pull in TensorFlow, wandb, ...)."""
    module = types.ModuleType(name)
    if path is not None:
        module.__path__ = [str(path)]
    for key, value in attrs.items():
        setattr(module, key, value)
    sys.modules[name] = module
    return module


def import_upstream(root: Path) -> dict:
    sys.path.insert(0, str(root))
    pkg = root / "prismatic"
    stub_package("prismatic", pkg)
    stub_package("prismatic.models", pkg / "models")
    stub_package("prismatic.models.backbones", pkg / "models" / "backbones")
    stub_package("prismatic.models.backbones.llm", pkg / "models" / "backbones" / "llm")
    stub_package("prismatic.training", pkg / "training")
    stub_package("prismatic.util", pkg / "util")
    stub_package("prismatic.vla", pkg / "vla")
    # action_heads.py imports diffusers for the diffusion head, which these fixtures do not use.
    stub_package("diffusers")
    stub_package("diffusers.schedulers")
    stub_package("diffusers.schedulers.scheduling_ddim", DDIMScheduler=object)

    from prismatic.extern.hf import configuration_prismatic, modeling_prismatic
    from prismatic.models import action_heads, film_vit_wrapper, projectors
    from prismatic.models.backbones.llm.prompting import base_prompter
    from prismatic.util import data_utils
    from prismatic.vla import action_tokenizer, constants

    return dict(
        config=configuration_prismatic,
        modeling=modeling_prismatic,
        heads=action_heads,
        film=film_vit_wrapper,
        projectors=projectors,
        prompter=base_prompter,
        data_utils=data_utils,
        action_tokenizer=action_tokenizer,
        constants=constants,
    )


def patch_timm_sizes() -> None:
    import timm

    create = timm.create_model

    def create_tiny(model_id: str, **kwargs: object):  # noqa: ANN202
        return create(model_id, **{**kwargs, **TINY_VIT[model_id]})

    timm.create_model = create_tiny


def tiny_llama_tokenizer():  # noqa: ANN201
    """A character-level tokenizer in Llama-2's layout: <unk>/<s>/</s> = 0/1/2, byte fallback at
    3..258, '▁' at 29871 (the id OpenVLA-OFT appends), 32000 pieces, then Prismatic's <PAD>."""
    import string

    from tokenizers import Tokenizer, decoders, models, normalizers
    from transformers import LlamaTokenizerFast

    vocab = {"<unk>": 0, "<s>": 1, "</s>": 2}
    for byte in range(256):
        vocab[f"<0x{byte:02X}>"] = len(vocab)
    for char in string.ascii_letters + string.digits + string.punctuation:
        vocab[char] = len(vocab)
    filler = (chr(c) for c in [*range(0x4E00, 0xA000), *range(0xAC00, 0xD7A4)])
    while len(vocab) < 32000:
        vocab["▁" if len(vocab) == 29871 else next(filler)] = len(vocab)
    model = models.BPE(vocab=vocab, merges=[], unk_token="<unk>", byte_fallback=True, fuse_unk=True)
    tok = Tokenizer(model)
    # Llama-2's tokenizer.json pipeline (legacy Metaspace via normalizer).
    tok.normalizer = normalizers.Sequence([normalizers.Prepend("▁"), normalizers.Replace(" ", "▁")])
    tok.decoder = decoders.Sequence(
        [
            decoders.Replace("▁", " "),
            decoders.ByteFallback(),
            decoders.Fuse(),
            decoders.Strip(" ", 1, 0),
        ]
    )
    fast = LlamaTokenizerFast(
        tokenizer_object=tok,
        bos_token="<s>",
        eos_token="</s>",
        unk_token="<unk>",
        add_bos_token=True,
        add_eos_token=False,
        padding_side="right",
        model_max_length=2048,
    )
    fast.add_special_tokens({"pad_token": "<PAD>"})  # prismatic/models/backbones/llm/llama2.py
    assert fast.convert_tokens_to_ids("▁") == 29871 and fast.pad_token_id == 32000
    return fast


@torch.no_grad()
def randomize(module: torch.nn.Module, generator: torch.Generator) -> None:
    """Every parameter from one seeded generator, at scales that keep each layer's signal alive
    (upstream's _init_weights gives 0.02 everywhere and 1e-5 LayerScales, which hide differences)."""
    for name, param in sorted(module.named_parameters()):
        leaf = name.rsplit(".", 1)[-1]
        values = torch.randn(param.shape, generator=generator)
        if "norm" in name and leaf == "weight":
            values = 1 + 0.1 * values
        elif leaf == "scale_factor":  # LayerScale
            values = 0.5 + 0.1 * values
        elif param.ndim >= 2 and "embed_tokens" not in name:
            values = values / math.sqrt(param[0].numel())
        elif "embed_tokens" not in name:
            values = 0.02 * values
        param.copy_(values.to(param.dtype))


def normalize_images(images: np.ndarray, n_cams: int) -> torch.Tensor:
    """(B, N, H, W, 3) uint8 -> OpenVLA pixel_values (B, 6N, H, W): per camera DINOv2 (ImageNet
    mean/std) then SigLIP (0.5/0.5) channels, as PrismaticImageProcessor's to_tensor + normalize at
    224 px (no resize: the images already have the backbone's size)."""
    x = torch.from_numpy(images).permute(0, 1, 4, 2, 3).float() / 255.0
    dino = (x - torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1)) / torch.tensor(
        [0.229, 0.224, 0.225]
    ).view(3, 1, 1)
    siglip = (x - 0.5) / 0.5
    per_cam = [torch.cat([dino[:, i], siglip[:, i]], dim=1) for i in range(n_cams)]
    return torch.cat(per_cam, dim=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--upstream", type=Path, required=True, help="openvla-oft checkout")
    parser.add_argument("--variant", choices=["libero", "aloha"], required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    variant = args.variant
    # prismatic/vla/constants.py picks the platform from the words on the command line, so
    # `--variant aloha` selects ALOHA_CONSTANTS; checked below.
    up = import_upstream(args.upstream.resolve())
    const = up["constants"]
    assert variant.upper() == const.ROBOT_PLATFORM, const.ROBOT_PLATFORM
    chunk, action_dim, proprio_dim = const.NUM_ACTIONS_CHUNK, const.ACTION_DIM, const.PROPRIO_DIM
    use_film = variant == "aloha"
    n_cams = 3 if variant == "aloha" else 2  # finetune.py --num_images_in_input of each recipe
    patch_timm_sizes()

    import torch.distributed as dist
    from peft import LoraConfig, PeftModel, get_peft_model
    from safetensors.torch import save_file
    from torch.nn.parallel import DistributedDataParallel as DDP
    from transformers import AutoConfig, AutoModelForVision2Seq

    OpenVLAConfig = up["config"].OpenVLAConfig
    OpenVLAForActionPrediction = up["modeling"].OpenVLAForActionPrediction
    AutoConfig.register("openvla", OpenVLAConfig)
    AutoModelForVision2Seq.register(OpenVLAConfig, OpenVLAForActionPrediction)

    # A fixed scratch folder beside the output: config.json records the base's path.
    tmp = args.out.parent / ".work"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    dist.init_process_group("gloo", init_method=f"file://{tmp.resolve()}/pg", rank=0, world_size=1)
    generator = torch.Generator().manual_seed(SEED)
    torch.manual_seed(SEED)
    rng = np.random.RandomState(SEED)

    # -- dataset statistics (OFT's schema), normalisation per platform ---------------------------
    def describe(dim: int) -> dict:
        low = rng.uniform(-2, -0.5, dim)
        high = rng.uniform(0.5, 2, dim)
        return {
            "mean": ((low + high) / 2).tolist(),
            "std": ((high - low) / 4).tolist(),
            "max": high.tolist(),
            "min": low.tolist(),
            "q01": (low * 0.9).tolist(),
            "q99": (high * 0.9).tolist(),
        }

    dataset = "libero_spatial_no_noops" if variant == "libero" else "aloha_fold_towel"
    action_stats = describe(action_dim)
    action_stats["mask"] = [True] * (action_dim - 1) + [False]
    statistics = {
        dataset: {
            "action": action_stats,
            "proprio": describe(proprio_dim),
            "num_transitions": 1000,
            "num_trajectories": 10,
        }
    }

    # -- the "pretrained" base VLA (what --vla_path points to) -----------------------------------
    tokenizer = tiny_llama_tokenizer()
    config = OpenVLAConfig(
        vision_backbone_id="dinosiglip-vit-so-224px",
        llm_backbone_id="llama2-7b-pure",
        arch_specifier="no-align+fused-gelu-mlp",
        use_fused_vision_backbone=True,
        image_resize_strategy="resize-naive",
        text_config=TINY_LLAMA,
        llm_max_length=2048,
        pad_token_id=32000,
        pad_to_multiple_of=64,
        norm_stats=statistics,
        n_action_bins=256,
    )
    base = OpenVLAForActionPrediction(config)
    randomize(base, generator)
    # Only the rows of ids the fixtures use stay random (specials, bytes, ASCII, '▁', <PAD>): the
    # rest of Llama-2's 32064 rows are zero so that the checkpoint compresses (a few MB in git).
    used = torch.zeros(TINY_LLAMA["vocab_size"], dtype=torch.bool)
    used[:512] = True
    used[[29871, 32000]] = True
    with torch.no_grad():
        base.language_model.model.embed_tokens.weight[~used] = 0
        base.language_model.lm_head.weight[~used] = 0
    base_dir = tmp / "base"
    base.to(torch.bfloat16).save_pretrained(base_dir)
    tokenizer.save_pretrained(base_dir)

    # -- finetune.py's setup: load bf16, LoRA all-linear, FiLM, DDP, heads ------------------------
    vla = AutoModelForVision2Seq.from_pretrained(base_dir, torch_dtype=torch.bfloat16)
    vla.vision_backbone.set_num_images_in_input(n_cams)
    lora_config = LoraConfig(
        r=LORA_RANK,
        lora_alpha=min(LORA_RANK, 16),
        lora_dropout=0.0,
        target_modules="all-linear",
        init_lora_weights="gaussian",
    )
    vla = get_peft_model(vla, lora_config)
    if use_film:
        vla.model.vision_backbone = up["film"].FiLMedPrismaticVisionBackbone(
            vision_backbone=vla.model.vision_backbone, llm_dim=vla.llm_dim
        )
    # "Training": every trainable tensor (LoRA A and B, FiLM) gets seeded random values.
    with torch.no_grad():
        for name, param in sorted(vla.named_parameters()):
            if param.requires_grad:
                scale = 0.05 if "lora_B" in name else 1 / math.sqrt(param.shape[-1])
                values = torch.randn(param.shape, generator=generator) * scale
                if "lm_head.lora_B" in name:  # peft 0.11's all-linear includes lm_head here
                    values[~used] = 0
                param.copy_(values.to(param.dtype))
    vla = DDP(vla, find_unused_parameters=True)
    proprio_projector = up["projectors"].ProprioProjector(
        llm_dim=vla.module.llm_dim, proprio_dim=proprio_dim
    )
    action_head = up["heads"].L1RegressionActionHead(
        input_dim=vla.module.llm_dim, hidden_dim=vla.module.llm_dim, action_dim=action_dim
    )
    randomize(proprio_projector, generator)
    randomize(action_head, generator)
    action_head = DDP(action_head.to(torch.bfloat16))  # init_module(..., to_bf16=True)
    proprio_projector = DDP(proprio_projector)

    # -- save_training_checkpoint -----------------------------------------------------------------
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    for stale in out.iterdir():
        if stale.is_file() and stale.name not in ("PROVENANCE",):
            stale.unlink()
    adapter_dir = tmp / "lora_adapter"
    (out / "dataset_statistics.json").write_text(json.dumps(statistics, indent=2))
    tokenizer.save_pretrained(out)
    vla.module.save_pretrained(adapter_dir)
    torch.save(proprio_projector.state_dict(), out / f"proprio_projector--{STEP}_checkpoint.pt")
    torch.save(action_head.state_dict(), out / f"action_head--{STEP}_checkpoint.pt")
    if use_film:
        torch.save(
            vla.module.vision_backbone.state_dict(), out / f"vision_backbone--{STEP}_checkpoint.pt"
        )
    # merge_lora_during_training: a fresh base + the adapter, merged, saved.
    merged = PeftModel.from_pretrained(
        AutoModelForVision2Seq.from_pretrained(base_dir, torch_dtype=torch.bfloat16), adapter_dir
    ).merge_and_unload()
    merged.save_pretrained(out)
    # Only the adapter's config travels (the weights are merged above; the FiLM run's vision LoRA
    # is inside vision_backbone--N): it records r and alpha.
    (out / "lora_adapter").mkdir(exist_ok=True)
    (out / "lora_adapter" / "adapter_config.json").write_text(
        (adapter_dir / "adapter_config.json").read_text()
    )

    # -- reference outputs: openvla_utils.py's loading, in fp32 -----------------------------------
    model = AutoModelForVision2Seq.from_pretrained(str(out), torch_dtype=torch.float32).eval()
    if use_film:  # _apply_film_to_vla
        model = get_peft_model(model, lora_config)
        model.model.vision_backbone = up["film"].FiLMedPrismaticVisionBackbone(
            vision_backbone=model.vision_backbone, llm_dim=model.llm_dim
        )
        state = torch.load(out / f"vision_backbone--{STEP}_checkpoint.pt", weights_only=True)
        model.model.vision_backbone.load_state_dict(state)
        model = model.model
    model.vision_backbone.set_num_images_in_input(n_cams)
    model = model.float().eval()

    def load_component(module: torch.nn.Module, name: str) -> torch.nn.Module:
        state = torch.load(out / f"{name}--{STEP}_checkpoint.pt", weights_only=True)
        state = {k.removeprefix("module."): v for k, v in state.items()}
        module.load_state_dict(state)
        return module.float().eval()

    head = load_component(
        up["heads"].L1RegressionActionHead(
            input_dim=model.llm_dim, hidden_dim=model.llm_dim, action_dim=action_dim
        ),
        "action_head",
    )
    proprio_proj = load_component(
        up["projectors"].ProprioProjector(llm_dim=model.llm_dim, proprio_dim=proprio_dim),
        "proprio_projector",
    )

    batch_size = 2
    coarse = rng.randint(0, 256, size=(batch_size, n_cams, 28, 28, 3)).astype(np.uint8)
    images = coarse.repeat(8, axis=2).repeat(8, axis=3)  # 224 px, compresses well
    proprio = rng.uniform(-1, 1, size=(batch_size, proprio_dim)).astype(np.float32)
    actions = rng.uniform(-1, 1, size=(batch_size, chunk, action_dim)).astype(np.float32)
    instructions = INSTRUCTIONS[variant]
    pixel_values = normalize_images(images, n_cams)

    refs: dict[str, torch.Tensor] = {}
    captured: dict[str, torch.Tensor] = {}
    model.vision_backbone.register_forward_hook(
        lambda _m, _a, output: captured.__setitem__("vision", output)
    )

    # Inference: predict_action, one sample at a time (upstream supports batch size 1 only).
    with torch.no_grad():
        for i, instruction in enumerate(instructions):
            prompt = f"In: What action should the robot take to {instruction.lower()}?\nOut:"
            input_ids = torch.tensor([tokenizer(prompt).input_ids])
            unnormalized, hidden = model.predict_action(
                input_ids=input_ids,
                attention_mask=torch.ones_like(input_ids, dtype=torch.bool),
                pixel_values=pixel_values[i : i + 1],
                unnorm_key=dataset,
                proprio=proprio[i],
                proprio_projector=proprio_proj,
                action_head=head,
                use_film=use_film,
            )
            refs[f"predict.{i}.actions_unnormalized"] = torch.from_numpy(unnormalized).float()
            refs[f"predict.{i}.actions"] = head.predict_action(hidden)[0]
            # The ids the LLM saw for the prompt: predict_action appends 29871 ('▁').
            refs[f"predict.{i}.prompt_ids"] = torch.cat([input_ids[0], torch.tensor([29871])])

        # Training: RLDSBatchTransform's prompt/labels, PaddedCollatorForActionPrediction, and the
        # L1 branch of finetune.py's run_forward_pass.
        action_tok = up["action_tokenizer"].ActionTokenizer(tokenizer)
        instances = []
        for i, instruction in enumerate(instructions):
            builder = up["prompter"].PurePromptBuilder("openvla")
            chunk_string = action_tok(actions[i][0]) + "".join(action_tok(actions[i][1:]))
            builder.add_turn(
                "human", f"What action should the robot take to {instruction.lower()}?"
            )
            builder.add_turn("gpt", chunk_string)
            ids = torch.tensor(tokenizer(builder.get_prompt(), add_special_tokens=True).input_ids)
            labels = ids.clone()
            labels[: -(len(chunk_string) + 1)] = const.IGNORE_INDEX
            per_cam = pixel_values[i].split(6, dim=0)
            instances.append(
                dict(
                    pixel_values=per_cam[0],
                    pixel_values_wrist=torch.cat(per_cam[1:], dim=0),
                    input_ids=ids,
                    labels=labels,
                    actions=actions[i],
                    proprio=proprio[i],
                )
            )
        collator = up["data_utils"].PaddedCollatorForActionPrediction(
            2048, tokenizer.pad_token_id, padding_side="right"
        )
        batch = collator(instances)
        output = model(
            input_ids=batch["input_ids"],
            attention_mask=batch["attention_mask"],
            pixel_values=batch["pixel_values"],
            labels=batch["labels"],
            output_hidden_states=True,
            proprio=batch["proprio"],
            proprio_projector=proprio_proj,
            use_film=use_film,
        )
        num_patches = model.vision_backbone.get_num_patches() * n_cams + 1  # + proprio token
        gt_ids = batch["labels"][:, 1:]
        mask = up["modeling"].get_current_action_mask(gt_ids) | up[
            "modeling"
        ].get_next_actions_mask(gt_ids)
        text_hidden = output.hidden_states[-1][:, num_patches:-1]
        actions_hidden = text_hidden[mask].reshape(batch_size, chunk * action_dim, -1)
        predicted = head.predict_action(actions_hidden)
        loss = torch.nn.L1Loss()(batch["actions"], predicted)

        refs["train.input_ids"] = batch["input_ids"]
        refs["train.attention_mask"] = batch["attention_mask"].long()
        refs["train.vision_features"] = captured["vision"]
        refs["train.projector_features"] = output.projector_features
        for layer, hidden in enumerate(output.hidden_states[:-1]):
            refs[f"train.hidden.{layer}"] = hidden  # input embeddings, then each layer before norm
        refs["train.actions"] = predicted
        refs["train.loss"] = loss.reshape(1)

    refs = {k: v.detach().contiguous() for k, v in refs.items()}
    save_file(refs, str(out / "reference_outputs.safetensors"))
    np.savez_compressed(
        out / "inputs.npz",
        images=images,
        proprio=proprio,
        actions=actions,
        instructions=np.array(instructions),
    )
    dist.destroy_process_group()
    shutil.rmtree(tmp)
    print(f"wrote {out}: loss {loss.item():.6f}")


if __name__ == "__main__":
    main()
