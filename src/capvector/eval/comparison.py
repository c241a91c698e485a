"""Differences between experiment arms with bootstrap intervals, from per-episode outcomes.

An arm is a set of training seeds, each evaluated on the same evaluation episodes at a list of
points (training steps, or zero-shot scene variants): a 0/1 array ``(training seeds, points,
evaluation seeds)``. A difference between two arms gets a 95% percentile interval from a
two-level bootstrap: each resample draws the evaluation seeds with replacement, the same draw for
both arms (outcomes pair by evaluation seed: an easy initial state is easy for every arm; an
evaluation seed is a (task, seed) pair, for LIBERO (task, official initial state)), and
each arm's training seeds with replacement, independently (seeds are not paired across arms).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np

from capvector.errors import CapVectorError


@dataclass
class ArmOutcomes:
    label: str
    points: list
    """Training steps (ascending ints) or variant names, one per column of ``outcomes``."""
    eval_seeds: list[Hashable]
    """The evaluation episodes, in ``outcomes``' order: (task, seed) pairs in reports."""
    outcomes: np.ndarray
    """(training seeds, points, evaluation seeds) of 0/1."""

    def __post_init__(self) -> None:
        shape = (self.outcomes.shape[1], self.outcomes.shape[2])
        if self.outcomes.ndim != 3 or shape != (len(self.points), len(self.eval_seeds)):
            raise ValueError(
                f"arm {self.label!r}: outcomes of shape {self.outcomes.shape} do not match "
                f"{len(self.points)} points x {len(self.eval_seeds)} evaluation seeds"
            )

    def rates(self) -> np.ndarray:
        """Success rate at each point over all seeds and episodes."""
        return self.outcomes.mean(axis=(0, 2))


def arm_from_episodes(
    label: str,
    per_seed: Sequence[dict[object, dict[Hashable, bool]]],
    points: Sequence | None = None,
) -> ArmOutcomes:
    """An arm from ``{point: {evaluation seed: success}}`` per training seed. Every seed must
    have every point on the same evaluation seeds (else the pairing would be wrong)."""
    if not per_seed:
        raise CapVectorError(f"arm {label!r} has no training seeds")
    points = list(points if points is not None else per_seed[0])
    eval_seeds = sorted(per_seed[0][points[0]])
    outcomes = np.zeros((len(per_seed), len(points), len(eval_seeds)))
    for t, by_point in enumerate(per_seed):
        for p, point in enumerate(points):
            episodes = by_point.get(point)
            if episodes is None or sorted(episodes) != eval_seeds:
                raise CapVectorError(
                    f"arm {label!r}, training seed {t}, point {point!r}: evaluated on "
                    f"{'no episodes' if episodes is None else f'{len(episodes)} other seeds'}, "
                    f"not the {len(eval_seeds)} evaluation seeds shared by every arm"
                )
            outcomes[t, p] = [episodes[s] for s in eval_seeds]
    return ArmOutcomes(label, points, eval_seeds, outcomes)


def area_under_curve(steps: Sequence[int], rates: np.ndarray) -> np.ndarray:
    """Trapezoid area under success-vs-steps divided by the last step (a mean success rate);
    ``rates`` (..., steps)."""
    x = np.asarray(steps, dtype=float)
    widths = np.diff(x) / (x[-1] - x[0])
    return ((rates[..., 1:] + rates[..., :-1]) / 2 * widths).sum(axis=-1)


class PairedBootstrap:
    """Resampled success rates of arms that share their evaluation seeds (see module doc)."""

    def __init__(
        self, eval_seeds: Sequence[Hashable], resamples: int = 10_000, seed: int = 0
    ) -> None:
        self.eval_seeds = list(eval_seeds)
        self.rng = np.random.default_rng(seed)
        n = len(self.eval_seeds)
        draws = self.rng.integers(0, n, size=(resamples, n))
        # Weight of each evaluation seed in each resample: the same for every arm (paired).
        self.eval_weights = np.stack([np.bincount(d, minlength=n) for d in draws]) / n

    def rates(self, arm: ArmOutcomes) -> np.ndarray:
        """(resamples, points) success rates: shared evaluation draw, own training-seed draw."""
        if arm.eval_seeds != self.eval_seeds:
            raise CapVectorError(
                f"arm {arm.label!r} was evaluated on other seeds than the arms it is compared with"
            )
        per_seed = np.einsum("tpe,be->btp", arm.outcomes, self.eval_weights)
        resamples, seeds = len(self.eval_weights), arm.outcomes.shape[0]
        drawn = self.rng.integers(0, seeds, size=(resamples, seeds))
        return per_seed[np.arange(resamples)[:, None], drawn].mean(axis=1)


def exact(differences: np.ndarray) -> np.ndarray:
    """Resampled differences of success rates, rid of float rounding: each is a difference of
    averages of counts, and summed in floats a difference that is 0 comes out as ±1e-17, which
    decided whether an interval touching 0 excluded it (bold, "detected") and which side of 0 a
    p-value counted it on. 12 decimals is far below one episode of any evaluation."""
    return np.round(differences, 12)


def interval(samples: np.ndarray, level: float = 0.95) -> list[float]:
    """Percentile interval (95% unless ``level`` says otherwise)."""
    tail = round(50 * (1 - level), 9)  # 2.5 exactly at 95%, as the committed reports were made
    low, high = np.percentile(samples, [tail, 100 - tail])
    return [float(low), float(high)]


def bootstrap_p_value(samples: np.ndarray) -> float:
    """Two-sided bootstrap p-value of "no difference": twice the smaller share of resampled
    differences on either side of 0 (ties count on both sides), at most 1."""
    return float(min(1.0, 2 * min(np.mean(samples <= 0), np.mean(samples >= 0))))


def holm(samples: Sequence[np.ndarray], alpha: float = 0.05) -> list[dict]:
    """Holm's step-down adjustment for a family of differences (every arm against one reference
    at one point; Holm 1979): the i-th smallest of m p-values is held to alpha / (m - i), and its
    adjusted p-value is the running maximum of (m - i) p. Per difference, in the order given:
    ``p`` (adjusted), ``level`` (the confidence its Holm rank asks for) and ``ci`` (the percentile
    interval at that level); a difference is detected at family-wise alpha when ``p`` < alpha."""
    m = len(samples)
    raw = [bootstrap_p_value(s) for s in samples]
    out: list[dict] = [{} for _ in samples]
    adjusted = 0.0
    for rank, i in enumerate(sorted(range(m), key=lambda i: raw[i])):
        adjusted = max(adjusted, min(1.0, (m - rank) * raw[i]))
        level = 1 - alpha / (m - rank)
        out[i] = {"p": adjusted, "level": level, "ci": interval(samples[i], level)}
    return out


def compare(
    arms: Sequence[ArmOutcomes],
    against: Sequence[str],
    resamples: int = 10_000,
    seed: int = 0,
) -> list[dict]:
    """Every arm against each label in ``against``: the difference in success at every point
    (and, for training steps, in the area under the curve), with its 95% bootstrap interval; and,
    where two or more arms are compared with one reference, Holm's adjustment over them at each
    point (``holm``: the family is those arms against that reference at that point)."""
    by_label = {a.label: a for a in arms}
    missing = [label for label in against if label not in by_label]
    if missing:
        raise CapVectorError(f"no arm named {missing}; arms: {list(by_label)}")
    bootstrap = PairedBootstrap(arms[0].eval_seeds, resamples, seed)
    samples = {a.label: bootstrap.rates(a) for a in arms}
    numeric = all(isinstance(p, int) for p in arms[0].points) and len(arms[0].points) > 1
    rows = []
    for reference in against:
        ref = by_label[reference]
        family: list[tuple[dict, np.ndarray]] = []
        for arm in arms:
            if arm.label == reference:
                continue
            if arm.points != ref.points:
                raise CapVectorError(
                    f"arms {arm.label!r} and {reference!r} have different points: "
                    f"{arm.points} and {ref.points}"
                )
            row: dict = {"arm": arm.label, "against": reference, "points": {}}
            difference = exact(samples[arm.label] - samples[reference])
            family.append((row, difference))
            point_estimate = arm.rates() - ref.rates()
            for p, point in enumerate(arm.points):
                row["points"][point] = {
                    "difference": float(point_estimate[p]),
                    "ci95": interval(difference[:, p]),
                }
            if numeric:
                auc = area_under_curve(arm.points, samples[arm.label])
                auc_ref = area_under_curve(ref.points, samples[reference])
                row["auc"] = {
                    "difference": float(
                        area_under_curve(arm.points, arm.rates())
                        - area_under_curve(ref.points, ref.rates())
                    ),
                    "ci95": interval(exact(auc - auc_ref)),
                }
            rows.append(row)
        if len(family) > 1:
            for p, point in enumerate(arms[0].points):
                adjusted = holm([difference[:, p] for _, difference in family])
                for (row, _), entry in zip(family, adjusted, strict=True):
                    row["points"][point]["holm"] = entry
    return rows


def format_difference(entry: dict) -> str:
    """``+12 pts (+3, +21)``; detected differences (interval excludes 0) in bold. An end that
    is not 0 but rounds to it keeps a decimal (``(+0.3, +17)``), so a bold interval never reads
    as touching 0."""
    low, high = entry["ci95"]
    text = f"{100 * entry['difference']:+.0f} pts ({_end(low)}, {_end(high)})"
    return f"**{text}**" if low > 0 or high < 0 else text


def _end(value: float) -> str:
    points = 100 * value
    return f"{points:+.1f}" if value != 0 and abs(points) < 0.5 else f"{points:+.0f}"
