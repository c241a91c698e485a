"""Tokenizers made locally, for the tiny presets (no model hub is reachable at run time)."""

from __future__ import annotations

from transformers import PreTrainedTokenizerFast

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
