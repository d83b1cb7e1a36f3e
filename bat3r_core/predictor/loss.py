"""Training loss of the dual point map predictor (DualPM loss and its robust BAT3R variant).

For every ground-truth-occupied (pixel, layer) entry, with confidences ``C_Q = 1 + exp(c_Q)`` and
``C_P = 1 + exp(c_P)`` and ``alpha = 1``::

    l = 0.5 * [(C_Q * rho(|dQ|) - alpha * log C_Q) + (C_P * rho(|dP|) - alpha * log C_P)]

averaged over the occupied entries of the whole batch, plus the binary cross-entropy of the occupancy logits
against the ground-truth occupancy (labels clamped to [0.01, 0.99]) averaged over the (pixel, layer) entries whose
pixel is inside the ground-truth layer-0 silhouette.

``rho`` is the squared error ``r**2`` for ``dualpm``. For ``robust`` it is the Huber function scaled to agree with
the squared error below the threshold: ``rho(r) = r**2`` for ``r <= delta`` and ``delta * (2 r - delta)`` above,
so it is continuously differentiable and equals the squared error as ``delta`` grows. ``huber_delta`` gives the
annealing schedule (log-linear from 0.1 m to 100 m over training, i.e. the threshold grows by the same factor every
step: outliers are down-weighted early, when bootstrapped targets and predictions disagree most, and the loss
becomes the plain DualPM loss by the end).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F

from bat3r_core.predictor.network import PointMapPrediction

#: Confidence logits are clamped to this maximum before exp() so ``C * rho`` cannot overflow to inf.
MAX_CONFIDENCE_LOGIT = 30.0
OCCUPANCY_LABEL_RANGE = (0.01, 0.99)


@dataclass(frozen=True)
class LossTerms:
    """Scalar tensors: ``total = regression + occupancy_weight * occupancy``; ``regression = 0.5 * (canonical
    + posed)``; ``canonical``/``posed`` are the mean per-entry terms ``C rho - alpha log C`` over occupied entries;
    ``occupied`` is the number of occupied entries (float)."""

    total: torch.Tensor
    regression: torch.Tensor
    canonical: torch.Tensor
    posed: torch.Tensor
    occupancy: torch.Tensor
    occupied: torch.Tensor


def huber_delta(step: int, total_steps: int, start: float = 0.1, end: float = 100.0) -> float:
    """Log-linear Huber threshold: ``start`` at step 0, ``end`` at step ``total_steps - 1`` (metres)."""
    if total_steps < 1 or step < 0:
        raise ValueError(f"huber_delta: expected step >= 0 and total_steps >= 1, got {step}, {total_steps}")
    t = min(step / max(total_steps - 1, 1), 1.0)
    return float(math.exp(math.log(start) + t * (math.log(end) - math.log(start))))


def _rho(squared: torch.Tensor, delta: float | None) -> torch.Tensor:
    if delta is None:
        return squared
    # clamp keeps sqrt's gradient finite where the quadratic branch is selected (r = 0 gives 0 * inf otherwise)
    r = torch.sqrt(squared.clamp_min(1e-12))
    return torch.where(squared <= delta * delta, squared, delta * (2.0 * r - delta))


def _confidence_term(pred: torch.Tensor, target: torch.Tensor, logits: torch.Tensor, alpha: float,
                     delta: float | None) -> torch.Tensor:
    logits = logits.clamp(max=MAX_CONFIDENCE_LOGIT)
    conf = 1.0 + torch.exp(logits)
    log_conf = F.softplus(logits)  # log(1 + exp(c)), stable
    return conf * _rho(((pred - target) ** 2).sum(-1), delta) - alpha * log_conf


def dual_pointmap_loss(prediction: PointMapPrediction, canonical_points: torch.Tensor, posed_points: torch.Tensor,
                       occupancy: torch.Tensor, kind: Literal["dualpm", "robust"] = "dualpm",
                       delta: float | None = None, alpha: float = 1.0, occupancy_weight: float = 1.0) -> LossTerms:
    """Loss of a batch (see the module docstring).

    Args:
        prediction: network output for B images, H x W, K layers.
        canonical_points: (B, H, W, K, 3) target Q, metres, canonical frame.
        posed_points: (B, H, W, K, 3) target P, metres, camera frame relative to the object depth.
        occupancy: (B, H, W, K) bool target occupancy; layer 0 is the silhouette.
        kind: ``dualpm`` (squared error) or ``robust`` (Huber with threshold ``delta``, required).
    """
    shape = prediction.canonical_points.shape
    for name, t in (("canonical_points", canonical_points), ("posed_points", posed_points)):
        if t.shape != shape:
            raise ValueError(f"{name}: expected shape {tuple(shape)}, got {tuple(t.shape)}")
    if occupancy.shape != shape[:-1]:
        raise ValueError(f"occupancy: expected shape {tuple(shape[:-1])}, got {tuple(occupancy.shape)}")
    if kind not in ("dualpm", "robust"):
        raise ValueError(f"kind: expected 'dualpm' or 'robust', got {kind!r}")
    if kind == "robust" and (delta is None or not delta > 0):
        raise ValueError(f"delta: the robust loss needs a Huber threshold > 0, got {delta}")
    huber = delta if kind == "robust" else None

    occ = occupancy.bool()
    n_occ = occ.sum()
    denom = n_occ.clamp_min(1).to(torch.float32)
    weight = occ.to(torch.float32)
    canonical = (_confidence_term(prediction.canonical_points.float(), canonical_points.float(),
                                  prediction.canonical_confidence_logits.float(), alpha, huber) * weight).sum() / denom
    posed = (_confidence_term(prediction.posed_points.float(), posed_points.float(),
                              prediction.posed_confidence_logits.float(), alpha, huber) * weight).sum() / denom

    lo, hi = OCCUPANCY_LABEL_RANGE
    labels = occ.to(torch.float32).clamp(lo, hi)
    silhouette = occ[..., :1].expand_as(occ).to(torch.float32)
    bce = F.binary_cross_entropy_with_logits(prediction.occupancy_logits.float(), labels, reduction="none")
    occupancy_term = (bce * silhouette).sum() / silhouette.sum().clamp_min(1.0)

    regression = 0.5 * (canonical + posed)
    return LossTerms(total=regression + occupancy_weight * occupancy_term, regression=regression,
                     canonical=canonical, posed=posed, occupancy=occupancy_term, occupied=n_occ.to(torch.float32))
