"""The objective contract: a loss term is an ``nn.Module`` (its parameters train and checkpoint)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable

from torch import Tensor, nn
from torch.utils.data import Dataset

from capvector.backbones.base import OutputRequest, VLABackbone, VLAOutput
from capvector.data.batch import Batch
from capvector.errors import CapVectorError
from capvector.registry import Registry


class Objective(nn.Module, ABC):
    """A named loss term. ``VLAModule`` adds ``weight * forward(...)`` to the action loss.

    ``weight`` is a plain attribute so a callback can schedule it; subclasses declare what they
    need from the forward pass in ``request`` (hidden layers, LM logits).
    """

    def __init__(self, name: str, weight: float = 1.0) -> None:
        super().__init__()
        self.name = name
        self.weight = float(weight)

    @property
    def request(self) -> OutputRequest:
        return OutputRequest()

    def bind(self, backbone: VLABackbone) -> None:  # noqa: B027 (optional hook, empty by default)
        """Build parameters that depend on the backbone (called once, before optimizers exist)."""

    def bind_data(self, dataset: Dataset, backbone: VLABackbone) -> None:  # noqa: B027
        """Build what depends on the training set (called once after ``bind``, when the fit's
        datamodule has a ``train_dataset``); empty by default."""

    @abstractmethod
    def forward(self, batch: Batch, output: VLAOutput, backbone: VLABackbone) -> Tensor:
        """The unweighted scalar loss of this term."""


def compute_losses(
    backbone: VLABackbone, objectives: Iterable[Objective], batch: Batch
) -> dict[str, Tensor]:
    """The unweighted loss terms of one training step, by name: ``action`` and each objective's,
    from one forward pass that keeps what every objective requests. ``VLAModule`` trains on them;
    the memory planner traces them."""
    objectives = list(objectives)
    request = OutputRequest()
    for objective in objectives:
        request = request.merged(objective.request)
    output = backbone(batch, request)
    losses = {"action": output.loss}
    for objective in objectives:
        losses[objective.name] = objective(batch, output, backbone)
    return losses


OBJECTIVES: Registry[type[Objective]] = Registry(
    "objective",
    modules=("capvector.objectives.spatial", "capvector.objectives.reasoning"),
    base=Objective,
    error=CapVectorError,
)
"""The auxiliary objectives by name (``spatial``, ``reasoning``, or ``module:Class``), for the
tools that attach one with its defaults (``backbone-info --flops``); configs name theirs by class
path (``AuxiliaryObjective``'s ``objective``)."""
