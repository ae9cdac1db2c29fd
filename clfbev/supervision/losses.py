"""Detection losses of CL-FusionBEV (paper eq. 5-9): focal classification, Smooth-L1 box
residuals with the sin-difference angle term, direction cross-entropy.

``L = l_cls L_cls + l_reg (L_reg + L_reg_theta) + l_dir L_dir``, every term summed over
anchors and divided by the number of positive anchors in the batch (clamped to >= 1), as in
SECOND / PointPillars: the loss scale then does not depend on how many anchors the grid has.
Optionally the velocity residuals get a loss of their own, balanced between moving and still
positives (:func:`velocity_loss`), or, with the velocity tower's gate, a moving/still
classification and a speed regressed on the moving positives (:func:`gated_velocity_loss`).
An unknown GT velocity has box weight 0 (its targets carry
no loss and no gradient).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.head import FlatPredictions, HeadOutput
from clfbev.settings import LossWeights
from clfbev.supervision.assign import AnchorTargets


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


# m/s: a positive whose GT is faster moves, for the balance of :func:`velocity_loss` and the gate
# of :func:`gated_velocity_loss`. Above the speed a parked object's label noise reaches, below a
# walker's pace: the benchmark's walkers stand at 0 (37%) or walk at 0.5-2 m/s, 46% of the
# walking ones below 1 m/s (nuScenes' own pedestrians walk at about 1.3 m/s).
MOVING_SPEED = 0.5


def velocity_loss(pred: Tensor, target: Tensor, known: Tensor, beta: float) -> Tensor:
    """The velocity loss of P positives, moving and still ones weighing the same in total.

    pred, target : (P, 2) ``vx, vy`` m/s (the residuals: anchors have velocity 0).
    known : (P,) bool, False where the GT velocity is unknown (no loss there).
    beta : Smooth-L1 beta, m/s.

    Why: three quarters of the positives stand still, and under an L1-type loss summed over
    them the best answer for features that do not yet tell a parked car from a moving one is 0,
    so the velocity never leaves 0. Weighting each group to half the total makes predicting 0
    cost as much as the moving half is fast. Returns a 0-d tensor (0 without a known velocity).
    """
    per_box = smooth_l1(pred - target, beta).sum(-1)                    # (P,)
    moving = known & (target.norm(dim=-1) > MOVING_SPEED)
    still = known & ~moving
    n_moving, n_still = moving.sum(), still.sum()
    groups = (n_moving > 0).to(pred.dtype) + (n_still > 0).to(pred.dtype)
    w = torch.where(moving, 1.0 / n_moving.clamp(min=1), 1.0 / n_still.clamp(min=1)) / groups.clamp(min=1)
    return (per_box * w * known.to(pred.dtype)).sum()


def gated_velocity_loss(pred: Tensor, moving_logit: Tensor, target: Tensor, known: Tensor,
                        beta: float, balanced: bool = False) -> tuple[Tensor, Tensor]:
    """(velocity loss, gate loss) of P positives, each a mean: the Smooth-L1 of the velocity over
    the moving positives only (GT faster than :data:`MOVING_SPEED`), or with ``balanced``
    :func:`velocity_loss` over all of them, and the binary cross-entropy of the moving logit over
    all positives with a known velocity.

    pred, target : (P, 2) ``vx, vy`` m/s; moving_logit : (P,); known : (P,) bool.
    beta : Smooth-L1 beta, m/s.

    Why: a regression over moving and still boxes together learns a speed shrunk toward the
    still majority's 0, and still boxes get a small speed of noise. Here the still ones never
    reach the regression; they only teach the gate, and decoding keeps the regressed velocity
    only where the gate fires (:func:`clfbev.head.decode`). The gate's cross-entropy is not
    rebalanced, so its probability stays calibrated and its 0.5 threshold is the choice that
    errs less often. Each is 0 (with a gradient path) where it has no box. With ``balanced`` the
    still boxes are regressed too (half the weight in total): the regression then learns what a
    still box looks like, and a gate that fires on one passes a speed near 0, not whatever a
    regression that never saw a still box gives it.
    """
    moving = known & (target.norm(dim=-1) > MOVING_SPEED)
    if balanced:
        loss_vel = velocity_loss(pred, target, known, beta)
    else:
        per_box = smooth_l1(pred - target, beta).sum(-1)                          # (P,)
        loss_vel = (per_box * moving.to(pred.dtype)).sum() / moving.sum().clamp(min=1)
    bce = F.binary_cross_entropy_with_logits(moving_logit, moving.to(moving_logit.dtype), reduction="none")
    loss_gate = (bce * known.to(bce.dtype)).sum() / known.sum().clamp(min=1)
    return loss_vel, loss_gate


def detection_loss(
    preds: HeadOutput | FlatPredictions,
    targets: AnchorTargets,
    weights: LossWeights = LossWeights(),
    velocity_balance: bool = False,
    velocity_beta: float = 1.0,
    velocity_weight: float = 0.2,
) -> dict[str, Tensor]:
    """Total detection loss (eq. 9) of a batch.

    Parameters
    ----------
    preds : head output for B samples, (B, N, ...) once flattened.
    targets : batched targets (:func:`clfbev.supervision.assign.stack_targets`), (B, N, ...).
    weights : loss weights.
    velocity_balance : the velocity residuals (7:) leave the Smooth-L1 of the box residuals for
        :func:`velocity_loss` (``velocity_beta``), weighted ``weights.reg * velocity_weight``.
        Predictions with ``moving_logits`` (the tower's gate) take :func:`gated_velocity_loss`
        instead (balanced with ``velocity_balance``), its two terms at the same weight.

    Returns
    -------
    dict of 0-d tensors: ``loss`` (eq. 9, differentiable), ``loss_cls``, ``loss_reg``,
    ``loss_reg_theta``, ``loss_dir`` (each already divided by the number of positives, before
    its l weight), ``loss_vel`` (the velocity residuals' share of ``loss_reg``, for the log),
    ``loss_moving`` (the gate's cross-entropy; with a gate only) and ``num_pos`` (float,
    unclamped).
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

    pos_index = torch.nonzero(positives.reshape(-1)).flatten()
    gated = flat.moving_logits is not None
    loss_reg, loss_reg_theta, loss_vel, loss_moving = _box_losses(flat, targets, pos_index, norm, weights,
                                                                  velocity_balance, velocity_beta)

    # Direction (eq. 8): only positives have a heading to classify.
    n_bins = flat.dir_logits.shape[-1]
    dir_logits = flat.dir_logits.reshape(-1, n_bins).index_select(0, pos_index)
    loss_dir = direction_cross_entropy(dir_logits, targets.dir_targets.reshape(-1)[pos_index]).sum() / norm

    total = weights.cls * loss_cls + weights.reg * (loss_reg + loss_reg_theta) + weights.dir * loss_dir
    if (velocity_balance or gated) and code_size > 7:
        total = total + weights.reg * velocity_weight * (loss_vel + loss_moving)
    losses = {
        "loss": total,
        "loss_cls": loss_cls,
        "loss_reg": loss_reg,
        "loss_reg_theta": loss_reg_theta,
        "loss_dir": loss_dir,
        "loss_vel": loss_vel.detach(),
        "num_pos": num_pos.detach(),
    }
    if gated:
        losses["loss_moving"] = loss_moving.detach()
    return losses


def _box_losses(flat: FlatPredictions, targets: AnchorTargets, pos_index: Tensor, norm: Tensor, weights: LossWeights,
                velocity_balance: bool, velocity_beta: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(loss_reg, loss_reg_theta, loss_vel, loss_moving) of the positives ``pos_index`` (eq. 6,
    7): Smooth-L1 per residual, the angle through sin-difference, each divided by ``norm``. Only
    positives have a box (their weights are 0 elsewhere), so only their rows are computed: a
    few hundred of the ~330k anchors of a 128 x 128 grid. Where the predictions have a gate the
    velocity is :func:`gated_velocity_loss`'s, else with ``velocity_balance``
    :func:`velocity_loss`'s, instead of a share of the Smooth-L1; ``loss_moving`` is the gate's
    (0 without one)."""
    velocity_own = velocity_balance or flat.moving_logits is not None
    code_size = flat.box_deltas.shape[-1]
    deltas = flat.box_deltas.reshape(-1, code_size).index_select(0, pos_index)
    box_targets = targets.box_targets.reshape(-1, code_size).index_select(0, pos_index)
    box_weights = targets.box_weights.reshape(-1, code_size).index_select(0, pos_index)
    pred_theta, target_theta = sin_difference(deltas[:, 6], box_targets[:, 6])
    diff = deltas - box_targets
    diff = torch.cat([diff[:, :6], (pred_theta - target_theta)[:, None], diff[:, 7:]], dim=-1)
    code_w = deltas.new_tensor(weights.code_weights[:code_size])
    if velocity_own:
        code_w[7:] = 0.0
    per_code = smooth_l1(diff, weights.smooth_l1_beta) * box_weights * code_w
    loss_reg_theta = per_code[:, 6].sum() / norm
    loss_reg = (per_code.sum() - per_code[:, 6].sum()) / norm
    loss_vel = per_code[:, 7:].sum() / norm
    loss_moving = deltas.new_zeros(())
    if velocity_own and code_size > 7:
        known = box_weights[:, 7] > 0
        if flat.moving_logits is not None:
            moving_logit = flat.moving_logits.reshape(-1).index_select(0, pos_index)
            loss_vel, loss_moving = gated_velocity_loss(deltas[:, 7:9], moving_logit, box_targets[:, 7:9], known,
                                                        velocity_beta, velocity_balance)
        else:
            loss_vel = velocity_loss(deltas[:, 7:9], box_targets[:, 7:9], known, velocity_beta)
    return loss_reg, loss_reg_theta, loss_vel, loss_moving
