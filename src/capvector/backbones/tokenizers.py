"""Tokenizers made locally, for the tiny presets (no model hub is reachable at run time), and
saved ones read from a local folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from transformers import PreTrainedTokenizerFast

from capvector.backbones.base import BackboneError

SPECIAL_TOKENS = ("<unk>", "<s>", "</s>", "<pad>")


def byte_level_tokenizer(model_max_length: int = 512) -> PreTrainedTokenizerFast:
    """A real HF fast tokenizer with one token per byte: any text, no training, 260 ids.

    Llama's special-token ids are kept (<unk>=0, <s>=1, </s>=2) so prompt-building code is the same
    for the tiny presets and for a checkpoint that ships Llama's own tokenizer.
    """
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers

    alphabet = sorted(pre_tokenizers.ByteLevel.alphabet())
    vocab = {token: i for i, token in enumerate([*SPECIAL_TOKENS, *alphabet])}
    backend = Tokenizer(models.BPE(vocab=vocab, merges=[], unk_token="<unk>"))
    backend.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False)
    backend.decoder = decoders.ByteLevel()
    return PreTrainedTokenizerFast(
        tokenizer_object=backend,
        bos_token="<s>",
        eos_token="</s>",
        unk_token="<unk>",
        pad_token="<pad>",
        model_max_length=model_max_length,
    )


def saved_tokenizer(folder: str | Path, hint: str) -> Any:
    """The tokenizer saved in ``folder``, read locally (never a hub name); ``hint`` says where to get
    one when the folder has none."""
    if not Path(folder, "tokenizer_config.json").is_file():
        raise BackboneError(f"tokenizer folder {folder} has no tokenizer_config.json; {hint}")
    from transformers import AutoTokenizer

    try:
        return AutoTokenizer.from_pretrained(str(folder))
    except Exception as exc:  # JSONDecodeError, or the tokenizers library's plain Exception
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise BackboneError(
            f"cannot read the tokenizer in {folder} ({reason}): its tokenizer.json or "
            "tokenizer_config.json is incomplete or corrupt; copy or export it again"
        ) from exc
