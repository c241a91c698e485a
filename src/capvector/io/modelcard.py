"""Model cards: the ``README.md`` that export and vector folders carry, as peft adapters and hub
models do, so a folder can be uploaded and read as it is.

The YAML header holds the fields the model hubs read (``library_name``, ``base_model``, ``tags``,
``pipeline_tag``), written by ``huggingface_hub.ModelCardData``; the body says what made the
folder: sources (local paths among them) and their fingerprints, λ, objectives, steps, the
command.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capvector.errors import CapVectorError
from capvector.io.hub import hub_id
from capvector.io.names import MODEL_CARD

if TYPE_CHECKING:
    from huggingface_hub import ModelCard

LIBRARY = "capvector"


def render_model_card(
    title: str,
    summary: str,
    facts: Mapping[str, Any],
    *,
    base_model: str | Sequence[str] | None = None,
    tags: Sequence[str] = (),
    command: str | None = None,
) -> str:
    """A model card: YAML header, title, one paragraph, a table of facts, and the command.

    ``base_model`` names what the weights came from, as the user gave it: hub ids go into the
    header's ``base_model`` (the hub links them), local paths into the body (a path in the header
    would be a broken link on the hub, and it names a folder on one machine only). The card is
    built with ``huggingface_hub``'s ``ModelCardData`` and checked by ``check_model_card``.
    """
    from huggingface_hub import ModelCard, ModelCardData

    bases = [base_model] if isinstance(base_model, str) else list(base_model or [])
    hub_bases = [b for b in bases if hub_id(b) is not None]
    local_bases = [b for b in bases if hub_id(b) is None]
    data = ModelCardData(
        library_name=LIBRARY,
        pipeline_tag="robotics",
        # The hub's base_model holds repo ids only (validate_repo_id refuses "org/name@main");
        # the revision the weights came from is kept in the body.
        base_model=list(dict.fromkeys(b.partition("@")[0] for b in hub_bases)) or None,
        tags=list(dict.fromkeys([LIBRARY, "robotics", *tags])),
    )
    lines = ["---", data.to_yaml(), "---", "", f"# {title}", "", summary, ""]
    facts = {
        **facts,
        "base model revision": ", ".join(b for b in hub_bases if "@" in b),
        "base model (local path)": ", ".join(local_bases),
    }
    rows = [(k, v) for k, v in facts.items() if v not in (None, [], {}, "")]
    if rows:
        lines += ["| | |", "|---|---|"]
        lines += [f"| {key} | {_cell(value)} |" for key, value in rows]
        lines.append("")
    if command:
        lines += ["Made with:", "", "```bash", command, "```", ""]
    card = ModelCard("\n".join(lines))
    check_model_card(card, "the model card")
    return str(card)


def check_model_card(card: ModelCard, where: str) -> None:
    """Refuse a card the hub would not read as ours: its YAML header must say
    ``library_name: capvector`` and its ``base_model`` hold hub ids only (a local path there is a
    broken link on the hub; paths belong in the body). ``where`` names the card in the error."""
    data = card.data
    if data.library_name != LIBRARY:
        raise CapVectorError(
            f"{where} has library_name {data.library_name!r}, not {LIBRARY!r}: it was not written "
            "by capvector; export or extract the folder with capvector"
        )
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id

    bases = [data.base_model] if isinstance(data.base_model, str) else data.base_model or []
    for base in map(str, bases):
        try:  # what the hub checks: a repo id, with no revision and no local path
            validate_repo_id(base)
        except HFValidationError:
            raise CapVectorError(
                f"{where} has base_model {base!r}, which is not a hub repo id (org/name): "
                "base_model holds repo ids only; put revisions and local paths in the card's body"
            ) from None


def read_model_card(folder: str | Path) -> ModelCard:
    """The checked model card of an export or vector folder."""
    from huggingface_hub import ModelCard

    path = Path(folder) / MODEL_CARD
    if not path.is_file():
        raise CapVectorError(
            f"{folder} has no {MODEL_CARD} (model card): export or extract it with capvector, "
            "which writes one"
        )
    try:
        card = ModelCard.load(path)
    except ValueError as err:  # a broken YAML header
        first = str(err).strip().splitlines()[0]
        raise CapVectorError(f"{path} is not a valid model card ({first})") from err
    check_model_card(card, str(path))
    return card


def write_model_card(folder: str | Path, card: str) -> None:
    (Path(folder) / MODEL_CARD).write_text(card)


def _cell(value: Any) -> str:
    if isinstance(value, float):
        text = f"{value:.6g}"
    elif isinstance(value, str):
        text = value
    else:
        text = json.dumps(value, ensure_ascii=False)
    return text.replace("|", "\\|").replace("\n", " ")
