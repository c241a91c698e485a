"""capvector.objectives.orthogonality: the orthogonal-regularisation loss."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from capvector.objectives.orthogonality import OrthogonalityLoss
from capvector.vectors import CapabilityVector, CapVectorError, LoraFactors

IN, OUT, R = 12, 10, 3


class Block(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.q_proj = nn.Linear(IN, OUT)
        self.up_proj = nn.Linear(OUT, IN, bias=False)


class Model(nn.Module):
    """Parameter names like a real decoder: ``model.layers.N.q_proj.weight``."""

    def __init__(self) -> None:
        super().__init__()
        self.model = nn.Module()
        self.model.layers = nn.ModuleList([Block(), Block()])
        self.head = nn.Linear(IN, 2)


KEYS = [
    "model.layers.0.q_proj.weight",
    "model.layers.0.q_proj.bias",
    "model.layers.1.q_proj.weight",
    "model.layers.1.up_proj.weight",
]


def _model(seed: int = 0) -> Model:
    torch.manual_seed(seed)
    return Model()


def _vector(model: nn.Module, seed: int = 1) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    params = dict(model.named_parameters())
    return {k: torch.randn(params[k].shape, generator=g) for k in KEYS}


def _projection_sq(
    model: nn.Module, meta: dict[str, torch.Tensor], vector: dict[str, torch.Tensor]
) -> float:
    """Σ ⟨θ − θ_meta, c⟩² / ‖c‖², in float64, the reference for full mode."""
    params = dict(model.named_parameters())
    total = 0.0
    for key, c in vector.items():
        delta = params[key].detach().double() - meta[key].double()
        total += float((delta * c.double()).sum()) ** 2 / float(c.double().square().sum())
    return total


def _lora_model(seed: int = 0, targets: tuple[str, ...] = ("q_proj", "up_proj")) -> nn.Module:
    from peft import LoraConfig, inject_adapter_in_model

    model = inject_adapter_in_model(
        LoraConfig(r=R, lora_alpha=6, target_modules=list(targets)), _model(seed)
    )
    g = torch.Generator().manual_seed(seed + 100)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "lora_" in name:
                p.copy_(0.3 * torch.randn(p.shape, generator=g))
    return model


def _lora_delta(layer: nn.Module) -> torch.Tensor:
    """s·B·A materialised (the tests' reference only)."""
    return (
        layer.scaling["default"] * layer.lora_B["default"].weight @ layer.lora_A["default"].weight
    )


def test_full_mode_is_exactly_zero_with_zero_gradient_for_an_orthogonal_update() -> None:
    model = _model()
    meta = {k: v.detach().clone() for k, v in model.named_parameters()}
    vector = _vector(model)
    for key in vector:  # c lives on the first rows, Δ on the others: ⟨Δ, c⟩ = 0 exactly
        vector[key][vector[key].shape[0] // 2 :] = 0.0
    loss = OrthogonalityLoss(vector).bind(model)
    assert loss().item() == 0.0
    with torch.no_grad():
        for key in KEYS:
            p = dict(model.named_parameters())[key]
            p[p.shape[0] // 2 :] += torch.randn_like(p[p.shape[0] // 2 :])
    value = loss()
    assert value.item() == 0.0
    value.backward()
    for key, p in model.named_parameters():
        if key in vector:
            assert p.grad is not None and torch.equal(p.grad, torch.zeros_like(p)), key

    # A generic update: the value is Σ ⟨Δ, c⟩²/‖c‖², and the gradient 2⟨Δ, c⟩ c/‖c‖².
    model.zero_grad()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    value = loss()
    assert value.item() == pytest.approx(_projection_sq(model, meta, vector), rel=1e-5)
    value.backward()
    key = "model.layers.1.up_proj.weight"
    p, c = dict(model.named_parameters())[key], vector[key]
    inner = float(((p.detach() - meta[key]).double() * c.double()).sum())
    torch.testing.assert_close(
        p.grad, (2 * inner / float(c.square().sum())) * c, rtol=1e-4, atol=1e-7
    )
    assert model.head.weight.grad is None  # the head is not in the vector
    assert float(loss.last_stats["num_terms"]) == len(KEYS)


def test_lora_mode_is_exactly_zero_for_an_orthogonal_update() -> None:
    model = _lora_model()
    layer = model.model.layers[0].q_proj
    c = torch.zeros(OUT, IN)
    c[:4] = torch.randn(4, IN)
    with torch.no_grad():
        layer.lora_B["default"].weight[:4] = 0.0  # Δ = s·B·A has no rows where c lives
    loss = OrthogonalityLoss(
        {"model.layers.0.q_proj.weight": c}, mode="lora", normalization="squared_cosine"
    )
    value = loss(backbone=model)  # binds on first use
    assert value.item() == 0.0
    value.backward()
    assert torch.equal(layer.lora_A["default"].weight.grad, torch.zeros(R, IN))
    assert torch.equal(layer.lora_B["default"].weight.grad, torch.zeros(OUT, R))


@pytest.mark.parametrize("normalization", ["squared_projection", "squared_cosine"])
def test_lora_mode_equals_the_materialised_update(normalization: str) -> None:
    model = _lora_model()
    vector = {k: v for k, v in _vector(_model()).items() if k.endswith(".weight")}
    loss = OrthogonalityLoss(vector, mode="lora", normalization=normalization).bind(model)
    value = loss()
    value.backward()

    # Reference: the same penalty on Δ = s·B·A formed explicitly, with autograd through it.
    reference = torch.zeros((), dtype=torch.float64)
    layers = {k: model.get_submodule(k.removesuffix(".weight")) for k in vector}
    factors = []
    for key, c in vector.items():
        a = layers[key].lora_A["default"].weight.detach().double().requires_grad_()
        b = layers[key].lora_B["default"].weight.detach().double().requires_grad_()
        delta = layers[key].scaling["default"] * b @ a
        inner, c_sq = (delta * c.double()).sum(), c.double().square().sum()
        if normalization == "squared_cosine":
            reference = reference + inner**2 / (c_sq * delta.square().sum())
        else:
            reference = reference + inner**2 / c_sq
        factors.append((key, a, b))
    reference.backward()
    assert value.item() == pytest.approx(reference.item(), rel=1e-5)
    for key, a, b in factors:
        torch.testing.assert_close(
            layers[key].lora_A["default"].weight.grad, a.grad.float(), rtol=1e-4, atol=1e-6
        )
        torch.testing.assert_close(
            layers[key].lora_B["default"].weight.grad, b.grad.float(), rtol=1e-4, atol=1e-6
        )
    if normalization == "squared_cosine":
        assert 0.0 < float(loss.last_stats["mean_abs_cos"]) < 1.0


def test_lora_mode_equals_full_mode_on_the_same_update() -> None:
    lora = _lora_model()
    vector = {k: v for k, v in _vector(_model()).items() if k.endswith(".weight")}
    lora_value = OrthogonalityLoss(vector, mode="lora").bind(lora)()

    plain = _model()  # same θ_meta as the LoRA model's base weights
    full = OrthogonalityLoss(vector, mode="full").bind(plain)
    with torch.no_grad():
        for key in vector:
            layer = lora.get_submodule(key.removesuffix(".weight"))
            plain.get_parameter(key).add_(_lora_delta(layer))
    assert full().item() == pytest.approx(lora_value.item(), rel=1e-4)


def test_lowrank_vector_path_equals_dense_path() -> None:
    g = torch.Generator().manual_seed(5)
    lowrank = {
        "model.layers.0.q_proj.weight": LoraFactors(
            torch.randn(OUT, 2, generator=g), torch.randn(2, IN, generator=g), 0.7
        ),
        "model.layers.1.up_proj.weight": LoraFactors(
            torch.randn(IN, 4, generator=g), torch.randn(4, OUT, generator=g)
        ),
    }
    dense = {k: f.rows() for k, f in lowrank.items()}

    for mode in ("full", "lora"):
        values, grads = [], []
        for vector in (dense, CapabilityVector(lowrank=lowrank)):
            model = _lora_model(seed=3) if mode == "lora" else _model(seed=3)
            loss = OrthogonalityLoss(vector, mode=mode).bind(model)
            if mode == "full":
                with torch.no_grad():
                    for p in model.parameters():
                        p.add_(
                            0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(9))
                        )
            value = loss()
            value.backward()
            values.append(value.item())
            grads.append(
                {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
            )
        assert values[0] == pytest.approx(values[1], rel=1e-4), mode
        assert grads[0].keys() == grads[1].keys() and grads[0]
        for name in grads[0]:
            torch.testing.assert_close(grads[0][name], grads[1][name], rtol=1e-3, atol=1e-6)


def test_olora_is_the_l1_norm_of_the_a_overlap() -> None:
    model = _lora_model()
    g = torch.Generator().manual_seed(2)
    c_a = torch.randn(2, IN, generator=g)
    vector = CapabilityVector(
        lowrank={"model.layers.0.q_proj.weight": LoraFactors(torch.randn(OUT, 2, generator=g), c_a)}
    )
    loss = OrthogonalityLoss(vector, mode="olora").bind(model)
    a_new = model.model.layers[0].q_proj.lora_A["default"].weight
    assert loss().item() == pytest.approx((c_a @ a_new.T).abs().sum().item(), rel=1e-6)
    with torch.no_grad():  # rows of A_new orthogonal to A_c's rows: no overlap, no penalty
        q, _ = torch.linalg.qr(torch.cat([c_a.T, torch.randn(IN, R, generator=g)], dim=1))
        a_new.copy_(q[:, 2 : 2 + R].T)
    assert loss().item() == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(CapVectorError, match="olora.*low-rank"):
        OrthogonalityLoss(
            {"model.layers.0.q_proj.weight": torch.randn(OUT, IN)}, mode="olora"
        ).bind(model)


def _train(weight: float, steps: int = 300) -> tuple[float, float]:
    """Full fine-tuning on a task that pulls θ along c (target = θ_meta + 0.5c + an orthogonal part).

    Returns (⟨Δ, c⟩/‖c‖², ‖Δ_orth − t_orth‖/‖t_orth‖) for one tensor."""
    model = _model()
    key = "model.layers.1.up_proj.weight"
    param = model.get_parameter(key)
    meta = param.detach().clone()
    g = torch.Generator().manual_seed(4)
    c = torch.randn(param.shape, generator=g)
    orth = torch.randn(param.shape, generator=g)
    orth -= (orth * c).sum() / c.square().sum() * c
    target = meta + 0.5 * c + orth
    loss = OrthogonalityLoss({key: c}, weight=weight).bind(model)
    optimizer = torch.optim.Adam([param], lr=0.05)
    for _ in range(steps):
        optimizer.zero_grad()
        total = (param - target).square().sum() + loss.weight * loss()
        total.backward()
        optimizer.step()
    delta = param.detach() - meta
    along = float((delta * c).sum() / c.square().sum())
    residual = delta - along * c
    return along, float((residual - orth).norm() / orth.norm())


def test_training_with_the_loss_keeps_the_update_off_c() -> None:
    along_free, miss_free = _train(weight=0.0)
    along_reg, miss_reg = _train(weight=1000.0)
    assert along_free == pytest.approx(
        0.5, abs=0.02
    )  # without the loss the task undoes/adds c freely
    assert abs(along_reg) < 0.02 * abs(along_free)  # with it the projection on c is driven to ~0
    assert (
        miss_free < 0.05 and miss_reg < 0.05
    )  # and the orthogonal part of the task is still learned


def test_anchors_survive_a_checkpoint_and_rebinding_keeps_them() -> None:
    model = _model()
    vector = _vector(model)
    loss = OrthogonalityLoss(vector).bind(model)
    assert set(loss.state_dict()) == {"anchors", "anchored"}  # c itself is not checkpointed
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.2 * torch.randn_like(p))
    trained = loss().item()
    assert trained > 0.0
    state = copy.deepcopy(loss.state_dict())

    resumed = OrthogonalityLoss(vector)
    resumed.load_state_dict(state)
    resumed.bind(model)  # θ is now trained; the loaded anchors must win over ⟨θ, c⟩
    assert torch.equal(resumed.anchors, state["anchors"])
    assert resumed().item() == pytest.approx(trained, rel=1e-12)

    rebound = OrthogonalityLoss(vector).bind(model)
    resumed.load_state_dict(rebound.state_dict())  # also after bind: loading overwrites anchors
    assert resumed().item() == 0.0
    resumed.reset_anchors()
    assert resumed.bind(model)().item() == 0.0


def test_dtype_casts_keep_the_vector_and_anchors_precise() -> None:
    model = _model()
    loss = OrthogonalityLoss(_vector(model)).bind(model)
    loss.to(torch.bfloat16)  # what bf16-true precision does to every submodule
    assert loss.anchors.dtype == torch.float64 and loss.c_0.dtype == torch.float32
    assert loss().item() == 0.0


def test_bind_errors_name_the_problem() -> None:
    model = _model()
    with pytest.raises(CapVectorError, match=r"lacks, e.g. `model.layers.5.q_proj.weight`"):
        OrthogonalityLoss({"model.layers.5.q_proj.weight": torch.ones(OUT, IN)}).bind(model)
    with pytest.raises(CapVectorError, match=r"shape \(3, 3\).*\(10, 12\)"):
        OrthogonalityLoss({"model.layers.0.q_proj.weight": torch.ones(3, 3)}).bind(model)
    with pytest.raises(CapVectorError, match="is a LoRA layer.*mode='lora'"):
        OrthogonalityLoss({"model.layers.0.q_proj.weight": torch.ones(OUT, IN)}).bind(_lora_model())
    with pytest.raises(ValueError, match="squared_cosine needs"):
        OrthogonalityLoss({"model.head.weight": torch.ones(2, IN)}, normalization="squared_cosine")
    with pytest.raises(CapVectorError, match="NaN/Inf"):
        OrthogonalityLoss({"model.head.weight": torch.full((2, IN), float("nan"))})
    with pytest.raises(RuntimeError, match="bind"):
        OrthogonalityLoss({"model.head.weight": torch.ones(2, IN)})()


def test_lora_mode_covers_trainable_non_lora_tensors_and_skips_frozen_ones() -> None:
    model = _lora_model(targets=("q_proj",))
    for name, p in model.named_parameters():
        p.requires_grad_("lora_" in name or name.startswith("model.layers.1.up_proj"))
    loss = OrthogonalityLoss(_vector(_model()), mode="lora").bind(model)
    kinds = {t.key: t.kind for t in loss._terms}
    assert kinds == {
        "model.layers.0.q_proj.weight": "lora",
        "model.layers.1.q_proj.weight": "lora",
        "model.layers.1.up_proj.weight": "full",  # trained in full next to the LoRA layers
    }
    assert loss.frozen == ["model.layers.0.q_proj.bias"]
