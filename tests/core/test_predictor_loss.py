"""DualPM loss: slow per-entry reference, zero gradient at a perfect prediction, robust variant, schedule."""
import math

import pytest
import torch

from bat3r_core.predictor.loss import dual_pointmap_loss, huber_delta
from bat3r_core.predictor.network import PointMapPrediction


def _random_case(seed=0, b=2, h=3, w=4, k=3):
    g = torch.Generator().manual_seed(seed)
    pred = PointMapPrediction(
        canonical_points=torch.randn(b, h, w, k, 3, generator=g, dtype=torch.float64),
        posed_points=torch.randn(b, h, w, k, 3, generator=g, dtype=torch.float64),
        occupancy_logits=torch.randn(b, h, w, k, generator=g, dtype=torch.float64),
        canonical_confidence_logits=torch.randn(b, h, w, k, generator=g, dtype=torch.float64),
        posed_confidence_logits=torch.randn(b, h, w, k, generator=g, dtype=torch.float64))
    occ = torch.rand(b, h, w, k, generator=g) < 0.6
    if k > 1:  # a background pixel whose deeper layers are "occupied": outside the silhouette
        occ[0, 0, 0, 0] = False
        occ[0, 0, 0, 1] = True
    q = torch.randn(b, h, w, k, 3, generator=g, dtype=torch.float64)
    p = torch.randn(b, h, w, k, 3, generator=g, dtype=torch.float64)
    return pred, q, p, occ


def _slow_reference(pred, q, p, occ, delta=None, alpha=1.0):
    """Per-entry Python loop, written straight from the formula."""
    def rho(r):
        if delta is None or r <= delta:
            return r * r
        return delta * (2 * r - delta)

    reg, n_occ, bce, n_sil = 0.0, 0, 0.0, 0
    b, h, w, k = occ.shape
    for i in range(b):
        for y in range(h):
            for x in range(w):
                for layer in range(k):
                    if occ[i, y, x, layer]:
                        terms = []
                        for pts, tgt, logit in ((pred.canonical_points, q, pred.canonical_confidence_logits),
                                                (pred.posed_points, p, pred.posed_confidence_logits)):
                            c = 1 + math.exp(float(logit[i, y, x, layer]))
                            r = math.sqrt(sum((float(pts[i, y, x, layer, d]) - float(tgt[i, y, x, layer, d])) ** 2
                                              for d in range(3)))
                            terms.append(c * rho(r) - alpha * math.log(c))
                        reg += 0.5 * (terms[0] + terms[1])
                        n_occ += 1
                    if occ[i, y, x, 0]:
                        label = min(max(float(occ[i, y, x, layer]), 0.01), 0.99)
                        s = 1 / (1 + math.exp(-float(pred.occupancy_logits[i, y, x, layer])))
                        bce += -(label * math.log(s) + (1 - label) * math.log(1 - s))
                        n_sil += 1
    return reg / n_occ + bce / n_sil, reg / n_occ, bce / n_sil


@pytest.mark.parametrize("kind,delta", [("dualpm", None), ("robust", 0.8), ("robust", 3.0)])
def test_loss_matches_slow_reference(kind, delta):
    pred, q, p, occ = _random_case()
    terms = dual_pointmap_loss(pred, q, p, occ, kind=kind, delta=delta)
    total, reg, bce = _slow_reference(pred, q, p, occ, delta=delta)
    assert terms.total.item() == pytest.approx(total, rel=1e-5)
    assert terms.regression.item() == pytest.approx(reg, rel=1e-5)
    assert terms.occupancy.item() == pytest.approx(bce, rel=1e-5)
    assert terms.occupied.item() == occ.sum().item()


def test_robust_equals_dualpm_for_large_delta():
    pred, q, p, occ = _random_case(seed=3)
    a = dual_pointmap_loss(pred, q, p, occ, kind="dualpm")
    b = dual_pointmap_loss(pred, q, p, occ, kind="robust", delta=100.0)
    assert b.total.item() == pytest.approx(a.total.item(), rel=1e-6)
    c = dual_pointmap_loss(pred, q, p, occ, kind="robust", delta=0.1)
    assert c.regression.item() < a.regression.item()  # residuals ~ N(0, 2): most are in the linear part


@pytest.mark.parametrize("kind", ["dualpm", "robust"])
def test_zero_gradient_at_perfect_prediction(kind):
    pred, q, p, occ = _random_case(seed=1)
    can = q.clone().requires_grad_(True)
    pos = p.clone().requires_grad_(True)
    pred = pred._replace(canonical_points=can, posed_points=pos)
    terms = dual_pointmap_loss(pred, q, p, occ, kind=kind, delta=0.1 if kind == "robust" else None)
    terms.total.backward()
    assert torch.count_nonzero(can.grad) == 0 and torch.count_nonzero(pos.grad) == 0
    # and away from it the xyz gradient is non-zero exactly on occupied entries
    pred2 = pred._replace(canonical_points=(q + 0.01).requires_grad_(True))
    dual_pointmap_loss(pred2, q, p, occ, kind=kind, delta=0.1 if kind == "robust" else None).total.backward()
    nonzero = pred2.canonical_points.grad.abs().sum(-1) > 0
    assert torch.equal(nonzero, occ)


def test_confidence_optimum_is_inverse_squared_error():
    # for a fixed error e, C e^2 - log C is minimised at C = 1 / e^2
    pred, q, p, occ = _random_case(seed=2, b=1, h=1, w=1, k=1)
    occ[:] = True
    e = 0.05
    q = pred.canonical_points.detach() + torch.tensor([e, 0.0, 0.0], dtype=torch.float64)
    logits = torch.linspace(0.0, 12.0, 2401, dtype=torch.float64)
    values = []
    for c in logits:
        pr = pred._replace(canonical_confidence_logits=c.reshape(1, 1, 1, 1))
        values.append(dual_pointmap_loss(pr, q, p, occ).canonical.item())
    best = 1 + math.exp(float(logits[int(torch.tensor(values).argmin())]))
    assert best == pytest.approx(1 / e ** 2, rel=0.01)


def test_huber_delta_schedule_is_log_linear():
    assert huber_delta(0, 1001) == pytest.approx(0.1)
    assert huber_delta(1000, 1001) == pytest.approx(100.0)
    assert huber_delta(500, 1001) == pytest.approx(math.sqrt(0.1 * 100.0))
    assert huber_delta(5000, 1001) == pytest.approx(100.0)
    with pytest.raises(ValueError, match="total_steps >= 1"):
        huber_delta(0, 0)


def test_loss_input_checks():
    pred, q, p, occ = _random_case()
    with pytest.raises(ValueError, match=r"posed_points: expected shape \(2, 3, 4, 3, 3\)"):
        dual_pointmap_loss(pred, q, p[:1], occ)
    with pytest.raises(ValueError, match="occupancy: expected shape"):
        dual_pointmap_loss(pred, q, p, occ[..., :1])
    with pytest.raises(ValueError, match="robust loss needs a Huber threshold"):
        dual_pointmap_loss(pred, q, p, occ, kind="robust")
    with pytest.raises(ValueError, match="kind: expected 'dualpm' or 'robust'"):
        dual_pointmap_loss(pred, q, p, occ, kind="l1")
