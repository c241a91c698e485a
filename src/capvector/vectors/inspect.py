"""``inspect_vector``: per-layer norms of a vector, cosines against another, and a PNG plot.

Tensors are grouped by decoder/encoder layer when their name has ``layers.N`` or ``blocks.N``
(e.g. ``language_model.model.layers.3``), otherwise by their module (``projector.fc1``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from tqdm.auto import tqdm

from capvector.io.outputs import atomic_write_file, check_output
from capvector.io.weights import CapVectorError, examples, row_chunks
from capvector.vectors.vector import VectorFolder

_LAYER = re.compile(r"^(?P<stack>(?:.*\.)?(?:layers|blocks))\.(?P<index>\d+)\.")


@dataclass
class GroupStats:
    """Norms of one group of tensors (a layer or a module) and, with ``against``, its cosine."""

    name: str
    stack: str | None
    """``language_model.model.layers`` for layer groups, None for module groups."""
    layer: int | None
    tensors: int = 0
    numel: int = 0
    norm_sq: float = 0.0
    shared_norm_sq: float = 0.0
    """‖c‖² over the tensors the other vector also has (the cosine's denominator)."""
    other_norm_sq: float | None = None
    dot: float | None = None

    @property
    def norm(self) -> float:
        return math.sqrt(self.norm_sq)

    @property
    def other_norm(self) -> float | None:
        return None if self.other_norm_sq is None else math.sqrt(self.other_norm_sq)

    @property
    def cosine(self) -> float | None:
        return _cosine(self.dot, self.shared_norm_sq, self.other_norm_sq)


@dataclass
class InspectReport:
    path: Path
    against: Path | None
    groups: list[GroupStats] = field(default_factory=list)
    num_tensors: int = 0
    lowrank_tensors: int = 0
    shared_tensors: int = 0
    """Tensors present in both vectors (cosines are over these)."""
    only_here: list[str] = field(default_factory=list)
    only_against: list[str] = field(default_factory=list)

    @property
    def norm(self) -> float:
        return math.sqrt(sum(g.norm_sq for g in self.groups))

    @property
    def cosine(self) -> float | None:
        """Cosine between the two vectors over their shared tensors."""
        if self.against is None:
            return None
        return _cosine(
            sum(g.dot or 0.0 for g in self.groups),
            sum(g.shared_norm_sq for g in self.groups),
            sum(g.other_norm_sq or 0.0 for g in self.groups),
        )

    def table(self) -> str:
        """A markdown table with one row per group and a total row."""
        header = ["group", "tensors", "params", "norm"]
        if self.against is not None:
            header += ["norm (against)", "cosine"]
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for g in self.groups:
            row = [g.name, str(g.tensors), f"{g.numel:,}", f"{g.norm:.4g}"]
            if self.against is not None:
                row += [_fmt(g.other_norm), _fmt(g.cosine, ".3f")]
            lines.append("| " + " | ".join(row) + " |")
        total = [
            "**total**",
            str(self.num_tensors),
            f"{sum(g.numel for g in self.groups):,}",
            f"{self.norm:.4g}",
        ]
        if self.against is not None:
            other = math.sqrt(sum(g.other_norm_sq or 0.0 for g in self.groups))
            total += [f"{other:.4g}", _fmt(self.cosine, ".3f")]
        lines.append("| " + " | ".join(total) + " |")
        return "\n".join(lines)


def group_of(key: str) -> tuple[str, str | None, int | None]:
    """(group name, layer stack, layer index) of a parameter name."""
    match = _LAYER.match(key)
    if match:
        return f"{match['stack']}.{match['index']}", match["stack"], int(match["index"])
    return key.rsplit(".", 1)[0] if "." in key else key, None, None


def inspect_vector(
    path: str | Path,
    /,
    against: str | Path | None = None,
    plot: str | Path | None = None,
    progress: bool = False,
) -> InspectReport:
    """Per-layer norms of the vector at ``path``; with ``against``, per-layer and overall cosines.

    Norms and inner products are computed from the stored tensors (low-rank ones through their
    factors' rows), chunk by chunk.

    Args:
        path: a vector folder.
        against: a second vector folder to compare with.
        plot: a PNG to write, of norms (and cosines) by layer.
        progress: show a tqdm bar.
    """
    if plot is not None:
        check_output(plot, overwrite=True, inputs=[path, against], what="--plot")
    vector = VectorFolder(path)
    other = VectorFolder(against) if against is not None else None
    report = InspectReport(Path(path), Path(against) if against is not None else None)
    keys = vector.keys()
    other_keys = set(other.keys()) if other else set()
    report.num_tensors = len(keys)
    report.lowrank_tensors = sum(vector.storage(k) == "lora" for k in keys)
    groups: dict[str, GroupStats] = {}
    for key in tqdm(keys, desc="inspect", unit="tensor", disable=not progress):
        name, stack, layer = group_of(key)
        g = groups.setdefault(name, GroupStats(name, stack, layer))
        info = vector.info(key)
        g.tensors += 1
        g.numel += info.numel
        paired = other is not None and key in other_keys
        if paired and tuple(other.info(key).shape) != tuple(info.shape):  # type: ignore[union-attr]
            raise CapVectorError(
                f"`{key}` has shape {info.shape} here and {other.info(key).shape} in {against}"  # type: ignore[union-attr]
            )
        for rows in row_chunks(info):
            chunk = vector.read(key, rows).double()
            norm_sq = float((chunk * chunk).sum())
            g.norm_sq += norm_sq
            if paired:
                g.shared_norm_sq += norm_sq
                o = other.read(key, rows).double()  # type: ignore[union-attr]
                g.dot = (g.dot or 0.0) + float((chunk * o).sum())
                g.other_norm_sq = (g.other_norm_sq or 0.0) + float((o * o).sum())
    if other is not None:
        report.shared_tensors = sum(k in other_keys for k in keys)
        report.only_here = [k for k in keys if k not in other_keys]
        report.only_against = sorted(other_keys - set(keys))
        if not report.shared_tensors:
            raise CapVectorError(
                f"{path} and {against} share no tensors ({examples(keys)} vs "
                f"{examples(sorted(other_keys))}); they cannot be compared"
            )
    report.groups = sorted(
        groups.values(),
        key=lambda g: (
            g.stack is not None,
            g.stack or g.name,
            g.layer if g.layer is not None else -1,
        ),
    )
    if plot is not None:
        plot_report(report, plot)
    return report


def plot_report(report: InspectReport, out: str | Path) -> Path:
    """Norm by layer, one line per layer stack (and cosine by layer with ``against``), as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stacks: dict[str, list[GroupStats]] = {}
    for g in report.groups:
        if g.stack is not None:
            stacks.setdefault(g.stack, []).append(g)
    if not stacks:
        raise CapVectorError(
            f"{report.path} has no `layers.N`/`blocks.N` tensors to plot by layer; use the table"
        )
    rows = 2 if report.against is not None else 1
    fig, axes = plt.subplots(rows, 1, figsize=(8, 3.2 * rows), squeeze=False, sharex=True)
    for stack, groups in stacks.items():
        layers = [g.layer for g in groups]
        line = axes[0][0].plot(layers, [g.norm for g in groups], marker="o", ms=3, label=stack)[0]
        if report.against is not None:
            axes[0][0].plot(
                layers,
                [g.other_norm or 0.0 for g in groups],
                ls="--",
                color=line.get_color(),
                label=f"{stack} (against)",
            )
            axes[1][0].plot(
                layers,
                [g.cosine if g.cosine is not None else math.nan for g in groups],
                marker="o",
                ms=3,
                color=line.get_color(),
                label=stack,
            )
    axes[0][0].set_ylabel("‖c‖ per layer")
    axes[0][0].set_title(report.path.name)
    axes[0][0].legend(fontsize=7)
    if report.against is not None:
        axes[1][0].axhline(0.0, color="grey", lw=0.5)
        axes[1][0].set_ylabel(f"cosine vs {report.against.name}")
    axes[-1][0].set_xlabel("layer")
    fig.tight_layout()
    target = Path(out)
    with atomic_write_file(target) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)
    return target


def _cosine(dot: float | None, a_sq: float | None, b_sq: float | None) -> float | None:
    if dot is None or not a_sq or not b_sq:
        return None
    return dot / math.sqrt(a_sq * b_sq)


def _fmt(x: float | None, spec: str = ".4g") -> str:
    return "–" if x is None else format(x, spec)
