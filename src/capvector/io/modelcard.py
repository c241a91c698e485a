"""Model cards: the ``README.md`` that export and vector folders carry, as peft adapters and hub
models do, so a folder can be uploaded and read as it is.

The YAML header holds the fields the model hubs read (``library_name``, ``base_model``, ``tags``,
``pipeline_tag``); the body says what made the folder: sources and their fingerprints, λ,
objectives, steps, the command.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from capvector.io.names import MODEL_CARD

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
    """A model card: YAML header, title, one paragraph, a table of facts, and the command."""
    header = [f"library_name: {LIBRARY}", "pipeline_tag: robotics"]
    bases = [base_model] if isinstance(base_model, str) else list(base_model or [])
    if bases:
        header.append("base_model:")
        header += [f"- {_yaml_string(b)}" for b in bases]
    header.append("tags:")
    header += [f"- {_yaml_string(t)}" for t in dict.fromkeys([LIBRARY, "robotics", *tags])]
    lines = ["---", *header, "---", "", f"# {title}", "", summary, ""]
    rows = [(k, v) for k, v in facts.items() if v not in (None, [], {}, "")]
    if rows:
        lines += ["| | |", "|---|---|"]
        lines += [f"| {key} | {_cell(value)} |" for key, value in rows]
        lines.append("")
    if command:
        lines += ["Made with:", "", "```bash", command, "```", ""]
    return "\n".join(lines)


def write_model_card(folder: str | Path, card: str) -> None:
    (Path(folder) / MODEL_CARD).write_text(card)


def _yaml_string(text: str) -> str:
    return json.dumps(str(text), ensure_ascii=False)  # a JSON string is a valid YAML scalar


def _cell(value: Any) -> str:
    if isinstance(value, float):
        text = f"{value:.6g}"
    elif isinstance(value, str):
        text = value
    else:
        text = json.dumps(value, ensure_ascii=False)
    return text.replace("|", "\\|").replace("\n", " ")
