"""Scale-out on Lightning's own strategies: FSDP2 sharding, activation checkpointing, and helpers
that let stateful pieces (export, merges, anchors) work on sharded (DTensor) parameters.
"""

from __future__ import annotations

import torch.distributed as dist
from torch import Tensor, nn

from capvector.errors import CapVectorError


def parallelize(
    backbone: nn.Module,
    units: list[nn.Module],
    extra_roots: list[nn.Module],
    mesh: object | None,
    activation_checkpointing: bool,
) -> None:
    """Apply activation checkpointing and, when ``mesh`` is given (``ModelParallelStrategy``),
    FSDP2 ``fully_shard`` to every unit, then to each extra root (objectives with parameters) and
    the backbone. Parameter names do not change, so checkpoints and exports keep their keys.
    """
    if activation_checkpointing:
        from torch.distributed._composable import checkpoint

        for unit in units:
            checkpoint(unit)
    if mesh is None:
        return
    from torch.distributed.fsdp import fully_shard

    if mesh["tensor_parallel"].size() > 1:  # type: ignore[index]
        raise CapVectorError(
            "tensor parallelism is not supported: use ModelParallelStrategy(data_parallel_size=N, "
            "tensor_parallel_size=1) for FSDP2"
        )
    data_parallel = mesh["data_parallel"]  # type: ignore[index]
    for unit in units:
        fully_shard(unit, mesh=data_parallel)
    for root in extra_roots:
        if any(True for _ in root.parameters()):
            fully_shard(root, mesh=data_parallel)
    fully_shard(backbone, mesh=data_parallel)


def is_sharded(module: nn.Module) -> bool:
    from torch.distributed.tensor import DTensor

    return any(isinstance(p, DTensor) for p in module.parameters())


def full_state_dict(module: nn.Module) -> dict[str, Tensor]:
    """The unsharded state dict on CPU. Collective when sharded: every rank must call it; only
    rank 0 receives the tensors (others get an empty dict)."""
    if not is_sharded(module):
        return {k: v.detach() for k, v in module.state_dict().items()}
    from torch.distributed.checkpoint.state_dict import StateDictOptions, get_model_state_dict

    options = StateDictOptions(full_state_dict=True, cpu_offload=True)
    return get_model_state_dict(module, options=options)


def is_rank_zero() -> bool:
    return not (dist.is_available() and dist.is_initialized()) or dist.get_rank() == 0


def like_parameter(tensor: Tensor, parameter: Tensor) -> Tensor:
    """``tensor`` (full, on CPU) placed and sharded the way ``parameter`` is."""
    from torch.distributed.tensor import DTensor, distribute_tensor

    if isinstance(parameter, DTensor):
        return distribute_tensor(
            tensor.to(parameter.device, parameter.dtype),
            parameter.device_mesh,
            parameter.placements,
        )
    return tensor.to(parameter.device, parameter.dtype)


def local_value(tensor: Tensor) -> Tensor:
    """A DTensor reduced to a plain tensor (differentiable); plain tensors pass through."""
    from torch.distributed.tensor import DTensor

    return tensor.full_tensor() if isinstance(tensor, DTensor) else tensor
