"""The still-state targets and loss (:mod:`clfbev.attributes`): each positive anchor learns
which of its class's two states at rest its object is in, parked or stopped, standing or
sitting, with or without a rider.

    loss_still = mean over the positive anchors whose object has a still state (0 or 1) of
                 BCE(still logit, state)

(moving vehicles and walkers, cones, barriers and pasted objects have none, and weigh 0). The
speed cannot tell these states apart; what can is where and how the object stands: a parked car
at the kerb, a stopped one in its lane behind another, a rider's points above a bicycle.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.supervision.assign import AnchorTargets


def still_targets(anchor: AnchorTargets, gt_still: list[Tensor]) -> Tensor:
    """(B, N) int64 the still state of each positive anchor's matched GT box, -1 elsewhere;
    ``gt_still`` B (M_i,) int64 per GT box (:class:`clfbev.data.Batch`), in the order the
    anchors were matched to."""
    out = torch.full_like(anchor.matched_gt, -1)
    for b, states in enumerate(gt_still):          # a loop over the B samples of the batch
        positive = anchor.matched_gt[b] >= 0
        out[b, positive] = states.to(out.device)[anchor.matched_gt[b, positive]]
    return out


def still_loss(still_logits: Tensor, targets: Tensor) -> Tensor:
    """0-d: the mean binary cross-entropy of ``still_logits`` (B, N) against ``targets`` (B, N)
    over the anchors with a target (>= 0); 0 (with a gradient path) where none has."""
    known = targets >= 0
    if not bool(known.any()):
        return still_logits.sum() * 0.0
    return F.binary_cross_entropy_with_logits(still_logits[known], targets[known].to(still_logits.dtype))
