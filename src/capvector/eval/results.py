"""Success rates of rollouts: the typed row, its 95% interval and the one table writer.

Every evaluation path (the validation loop's logs aside) ends here: ``capvector evaluate`` and
``capvector recipe`` print :func:`format_success_table`, ``capvector sweep-scale`` puts
:func:`success_cell` in its λ table. No simulator or torch import: reading results is cheap.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from capvector.envs.base import DEFAULT_ROBOT


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate (robust at 0 and 1 with few episodes)."""
    if n == 0:
        return 0.0, 0.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def success_cell(successes: int, episodes: int) -> str:
    """``40% (4/10; 17%–69%)``: rate, counts and the 95% Wilson interval in one table cell."""
    if episodes == 0:
        return "–"
    low, high = wilson_interval(successes, episodes)
    return f"{successes / episodes:.0%} ({successes}/{episodes}; {low:.0%}–{high:.0%})"


def best_scale(rows: list[dict[str, Any]]) -> float:
    """The λ of ``capvector sweep-scale``'s rows (its ``sweep.json``) with the highest success
    rate; ties (and sweeps without rollouts) go to the lowest held-out L1. Here, not in the sweep's
    module, so that the recipe reads it without importing Lightning."""
    return min(rows, key=lambda r: (-r.get("success_rate", 0.0), r.get("held_out_l1", 0.0)))[
        "scale"
    ]


class _Episode(Protocol):
    success: bool
    steps: int
    reason: str | None
    task: str
    robot: str
    variant: str | None
    seed: int


@dataclass(frozen=True)
class SuccessRow:
    """The episodes of one (task, robot, variant): how many, how many succeeded, why others not."""

    task: str
    robot: str
    episodes: int
    successes: int
    mean_steps: float
    variant: str | None = None
    failures: tuple[str, ...] = ()
    label: str | None = None
    """Whose row it is in a table of several runs (e.g. a recipe's stage)."""
    instruction: str | None = None
    """The task's language instruction (LIBERO's tasks are told apart by it)."""
    outcomes: tuple[tuple[int, bool], ...] = field(default=(), compare=False)
    """(seed, success) of every episode, so intervals paired by seed can be recomputed."""
    stack: str | None = None
    """The simulator stack that produced it (``Suite.provenance``), e.g. ``port (robosuite 1.5.2,
    MuJoCo 3.9.0)`` against ``upstream LIBERO (robosuite 1.4.0, MuJoCo 2.3.7)``."""
    renderer: str | None = None
    """Who drew the policy's images (LIBERO: ``fast`` or ``official``)."""

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes if self.episodes else 0.0

    @property
    def ci95(self) -> tuple[float, float]:
        return wilson_interval(self.successes, self.episodes)

    def to_dict(self) -> dict[str, Any]:
        """JSON form; ``success_rate`` and ``ci95`` are included for readers without this class."""
        return {
            "task": self.task, "robot": self.robot, "variant": self.variant,
            "episodes": self.episodes, "successes": self.successes,
            "success_rate": self.success_rate, "ci95": list(self.ci95),
            "mean_steps": self.mean_steps, "failures": list(self.failures),
            **({"instruction": self.instruction} if self.instruction else {}),
            **({"stack": self.stack} if self.stack else {}),
            **({"renderer": self.renderer} if self.renderer else {}),
            "outcomes": [[seed, bool(ok)] for seed, ok in self.outcomes],
        }  # fmt: skip

    @classmethod
    def from_dict(cls, row: Mapping[str, Any], label: str | None = None) -> SuccessRow:
        return cls(
            task=row["task"], robot=row["robot"], episodes=int(row["episodes"]),
            successes=int(row["successes"]), mean_steps=float(row.get("mean_steps", 0.0)),
            variant=row.get("variant"), failures=tuple(row.get("failures", ())),
            label=label, instruction=row.get("instruction"), outcomes=tuple((int(a), bool(b)) for a, b in row.get("outcomes", ())),
            stack=row.get("stack"), renderer=row.get("renderer"),
        )  # fmt: skip


def metric_key(task: str, robot: str, variant: str | None = None) -> str:
    """What a success rate is named after (``val/success_rate_by_task/<key>``, ``episodes.csv``'s task):
    the task, then the arm and the scene variant when they are not the defaults."""
    arm = "" if robot == DEFAULT_ROBOT else f"_{robot}"
    return f"{task}{arm}" + (f"_{variant}" if variant else "")


def success_rows(results: Iterable[_Episode]) -> list[SuccessRow]:
    """One row per (task, robot, variant), in the order they first appear."""
    groups: dict[tuple[str, str, str | None], list[_Episode]] = {}
    for r in results:
        groups.setdefault((r.task, r.robot, r.variant), []).append(r)
    rows = []
    for (task, robot, variant), episodes in groups.items():
        rows.append(
            SuccessRow(
                task, robot, len(episodes), sum(r.success for r in episodes),
                sum(r.steps for r in episodes) / len(episodes), variant,
                tuple(sorted({r.reason for r in episodes if r.reason})),
                outcomes=tuple((r.seed, r.success) for r in episodes),
            )
        )  # fmt: skip
    return rows


def pooled_row(rows: Sequence[SuccessRow], task: str) -> SuccessRow:
    """All episodes of ``rows`` as one row named ``task`` (a suite's total)."""
    episodes = sum(r.episodes for r in rows)
    steps = sum(r.mean_steps * r.episodes for r in rows)
    return SuccessRow(
        task, rows[0].robot if rows else DEFAULT_ROBOT, episodes, sum(r.successes for r in rows),
        steps / episodes if episodes else 0.0,
        failures=tuple(sorted({f for r in rows for f in r.failures})),
        stack=_shared(r.stack for r in rows), renderer=_shared(r.renderer for r in rows),
    )  # fmt: skip


def _shared(values: Iterable[str | None]) -> str | None:
    """The one value every row has, else None (rows of several stacks pooled)."""
    distinct = set(values)
    return distinct.pop() if len(distinct) == 1 else None


INSTRUCTION_WIDTH = 48
"""Characters of an instruction a table shows."""


def format_success_table(rows: Sequence[SuccessRow]) -> str:
    """Markdown: a label column when rows carry labels, a variant column when any has one, an
    instruction column (shortened) when any has one; the stack and renderer that produced the
    rows in a line under it (a column when they differ)."""
    labelled = any(r.label for r in rows)
    varied = any(r.variant for r in rows)
    told = any(r.instruction for r in rows)
    head = ["stage"] * labelled + ["task"] + ["instruction"] * told + ["robot"]
    head += ["variant"] * varied + ["success (n; 95% CI)", "mean steps"]
    # Which stack and renderer: a line under the table when every row shares them, else a column
    # (a recipe's table of stages run on the LIBERO port and on upstream LIBERO).
    stacks = {(r.stack, r.renderer) for r in rows if r.stack or r.renderer}
    mixed = bool(stacks) and len({(r.stack, r.renderer) for r in rows}) > 1
    head += ["stack"] * mixed
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r.label or ""] * labelled + [r.task]
        cells += [_shorten(r.instruction or "", INSTRUCTION_WIDTH)] * told + [r.robot]
        cells += [r.variant or "–"] * varied
        cells += [success_cell(r.successes, r.episodes), f"{r.mean_steps:.1f}"]
        cells += [_provenance(r)] * mixed
        lines.append("| " + " | ".join(cells) + " |")
    if stacks and not mixed:
        lines.append(f"\nStack: {_provenance(rows[0])}.")
    return "\n".join(lines)


def _provenance(row: SuccessRow) -> str:
    return provenance_label(row.stack, row.renderer)


NOT_RECORDED = "not recorded"
"""The stack of results written before results said which stack produced them."""


def provenance_label(stack: str | None, renderer: str | None) -> str:
    """``port (robosuite 1.5.2, MuJoCo 3.9.0), fast renderer``, or :data:`NOT_RECORDED`."""
    if not stack:
        return NOT_RECORDED
    return stack + (f", {renderer} renderer" if renderer else "")


def _shorten(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 1].rstrip() + "…"
