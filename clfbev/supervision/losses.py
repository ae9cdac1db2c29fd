"""Detection losses of CL-FusionBEV (paper eq. 5-9): focal classification, Smooth-L1 box
residuals with the sin-difference angle term, direction cross-entropy.

``L = l_cls L_cls + l_reg (L_reg + L_reg_theta) + l_dir L_dir``, every term summed over
anchors and divided by the number of positive anchors in the batch (clamped to >= 1), as in
SECOND / PointPillars: the loss scale then does not depend on how many anchors the grid has.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.assign import Targets
from clfbev.head import FlatPredictions, HeadOutput


@dataclass(frozen=True)
class LossWeights:
    """Weights of eq. 9 and of the individual residuals.

    cls, reg, dir : l_cls, l_reg, l_dir.
    depth : weight of the camera's lidar-supervised depth loss (:mod:`clfbev.depth`; BEVDepth
        uses 3.0); 0 turns the supervision off (the ablation). Unused by the ``lidar`` variant.
    semantic : weight of the camera's perspective class loss (:mod:`clfbev.perspective`); 0 (the
        default) builds no perspective head. Unused by the ``lidar`` variant.
    code_weights : per residual ``(dx, dy, dz, dl, dw, dh, dtheta, vx, vy)``; velocity is
        down-weighted (0.2) because it is noisy (from a few sweeps) and would otherwise pull
        the shared features away from localisation early in training.
    focal_alpha, focal_gamma : focal loss parameters (paper: 0.25 and 2).
    smooth_l1_beta : Smooth-L1 transition point; 1/9 is SECOND's ``sigma = 3``.
    """

    cls: float = 1.0
    reg: float = 2.0
    dir: float = 0.2
    depth: float = 3.0
    semantic: float = 0.0
    code_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.2, 0.2)
    focal_alpha: float = 0.25
    focal_gamma: float = 2.0
    smooth_l1_beta: float = 1.0 / 9.0


def sigmoid_focal_loss(logits: Tensor, targets: Tensor, alpha: float = 0.25, gamma: float = 2.0) -> Tensor:
    """Binary focal loss (eq. 5), element-wise, no reduction.

    ``FL = -alpha_t (1 - p_t)^gamma log(p_t)`` with ``p = sigmoid(logit)``,
    ``p_t = p`` for target 1 and ``1 - p`` for target 0, ``alpha_t = alpha`` resp. ``1 - alpha``.

    Parameters
    ----------
    logits : (...) raw scores.
    targets : (...) float in {0, 1}, same shape.

    Returns
    -------
    (...) loss per element.
    """
    p = torch.sigmoid(logits)
    # log(p_t) from the logits directly: stable for confident predictions, where log(sigmoid)
    # would underflow to -inf.
    ce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    p_t = p * targets + (1.0 - p) * (1.0 - targets)
    alpha_t = alpha * targets + (1.0 - alpha) * (1.0 - targets)
    return alpha_t * (1.0 - p_t).pow(gamma) * ce


def smooth_l1(x: Tensor, beta: float) -> Tensor:
    """Smooth-L1 (Huber / beta), element-wise: ``0.5 x^2 / beta`` for ``|x| < beta``, else
    ``|x| - 0.5 beta``; ``beta = 0`` is plain L1."""
    ax = x.abs()
    if beta <= 0:
        return ax
    return torch.where(ax < beta, 0.5 * ax * ax / beta, ax - 0.5 * beta)


def sin_difference(pred_angle: Tensor, target_angle: Tensor) -> tuple[Tensor, Tensor]:
    """The sin-difference trick (eq. 7): encode ``(a, b) -> (sin a cos b, cos a sin b)``.

    Their difference is ``sin(a - b)``, so a Smooth-L1 on the encoded pair penalises
    ``sin(theta_pred - theta_gt)``: zero for an error of exactly pi and smooth across the +-pi
    wrap. The pi ambiguity is resolved by the direction classifier.

    pred_angle, target_angle : (...) radians (the dtheta residuals).
    Returns the encoded (pred, target), each (...).
    """
    return torch.sin(pred_angle) * torch.cos(target_angle), torch.cos(pred_angle) * torch.sin(target_angle)


def direction_cross_entropy(logits: Tensor, targets: Tensor) -> Tensor:
    """Direction classification loss (eq. 8), element-wise cross-entropy.

    logits : (..., n_bins); targets : (...) int64 bins -> (...) loss.
    """
    n_bins = logits.shape[-1]
    return F.cross_entropy(logits.reshape(-1, n_bins), targets.reshape(-1), reduction="none").view(targets.shape)


def detection_loss(
    preds: HeadOutput | FlatPredictions,
    targets: Targets,
    weights: LossWeights = LossWeights(),
) -> dict[str, Tensor]:
    """Total detection loss (eq. 9) of a batch.

    Parameters
    ----------
    preds : head output for B samples, (B, N, ...) once flattened.
    targets : batched targets (:func:`clfbev.assign.stack_targets`), (B, N, ...).
    weights : loss weights.

    Returns
    -------
    dict of 0-d tensors: ``loss`` (eq. 9, differentiable), ``loss_cls``, ``loss_reg``,
    ``loss_reg_theta``, ``loss_dir`` (each already divided by the number of positives, before
    its l weight), ``loss_vel`` (the velocity residuals' share of ``loss_reg``, for the log)
    and ``num_pos`` (float, unclamped).
    """
    flat = preds.flatten() if isinstance(preds, HeadOutput) else preds
    if flat.cls_logits.shape != targets.labels.shape:
        raise ValueError(
            f"predictions {tuple(flat.cls_logits.shape)} and targets {tuple(targets.labels.shape)} "
            "must both be (B, N) with the same anchors"
        )
    code_size = flat.box_deltas.shape[-1]
    if len(weights.code_weights) < code_size:
        raise ValueError(f"need {code_size} code weights, got {len(weights.code_weights)}")
    positives = targets.positives
    num_pos = positives.sum().to(flat.cls_logits.dtype)
    # Normalise by the positives of the whole batch; with DDP each rank uses its own count.
    norm = num_pos.clamp(min=1.0)

    # Classification (eq. 5): one logit per anchor, target 1 on positives.
    focal = sigmoid_focal_loss(
        flat.cls_logits, positives.to(flat.cls_logits.dtype), weights.focal_alpha, weights.focal_gamma
    )
    loss_cls = (focal * targets.cls_weights).sum() / norm

    # Box residuals (eq. 6, 7): Smooth-L1 per residual, the angle through sin-difference. Only
    # positives have a box (their weights are 0 elsewhere), so only their rows are computed:
    # a few hundred of the ~330k anchors of a 128 x 128 grid.
    pos_index = torch.nonzero(positives.reshape(-1)).flatten()
    deltas = flat.box_deltas.reshape(-1, code_size).index_select(0, pos_index)
    box_targets = targets.box_targets.reshape(-1, code_size).index_select(0, pos_index)
    box_weights = targets.box_weights.reshape(-1, code_size).index_select(0, pos_index)
    pred_theta, target_theta = sin_difference(deltas[:, 6], box_targets[:, 6])
    diff = deltas - box_targets
    diff = torch.cat([diff[:, :6], (pred_theta - target_theta)[:, None], diff[:, 7:]], dim=-1)
    code_w = deltas.new_tensor(weights.code_weights[:code_size])
    per_code = smooth_l1(diff, weights.smooth_l1_beta) * box_weights * code_w
    loss_reg_theta = per_code[:, 6].sum() / norm
    loss_reg = (per_code.sum() - per_code[:, 6].sum()) / norm
    loss_vel = per_code[:, 7:].sum() / norm

    # Direction (eq. 8): only positives have a heading to classify.
    n_bins = flat.dir_logits.shape[-1]
    dir_logits = flat.dir_logits.reshape(-1, n_bins).index_select(0, pos_index)
    loss_dir = direction_cross_entropy(dir_logits, targets.dir_targets.reshape(-1)[pos_index]).sum() / norm

    total = weights.cls * loss_cls + weights.reg * (loss_reg + loss_reg_theta) + weights.dir * loss_dir
    return {
        "loss": total,
        "loss_cls": loss_cls,
        "loss_reg": loss_reg,
        "loss_reg_theta": loss_reg_theta,
        "loss_dir": loss_dir,
        "loss_vel": loss_vel.detach(),
        "num_pos": num_pos.detach(),
    }
