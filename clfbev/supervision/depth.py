"""Depth supervision of the camera branch from the lidar (BEVDepth, Li et al. 2023).

A lift-splat camera trained only through the detection loss has to discover depth from a few
thousand boxes, and on small data it does not (BEVDepth's ablation). The lidar measures the
depth of every pixel it hits, so:

1. project the key-frame lidar points into each camera through the same intrinsics,
   extrinsics and image augmentation that lift-splat uses (``img_aug @ K @ T_cam_from_lidar``),
   so that a target cell is exactly the feature cell whose frustum the point lies in;
2. per feature cell (stride s: cell (i, j) covers augmented pixels [j s, (j + 1) s) x
   [i s, (i + 1) s)) keep the NEAREST depth (the surface the cell sees, not what is behind it),
   as the bin of :mod:`clfbev.geometry` (``floor((z - d_min) / step)``, camera z);
3. a binary cross-entropy between the predicted depth distribution and the one-hot bin,
   summed over bins and averaged over the cells that have a target (cells without a point,
   and depths outside the bins, are ignored).

Only key-frame points (time lag 0) are used: the earlier sweeps are motion-compensated for the
ego but not for moving objects. Points pasted by GT-paste are excluded: they have no pixels.

The oracle lift (``ModelConfig.cam_oracle_depth``) lifts with these very bins: the training
collate hands its depth targets to the model as ``Batch.depth_bins``
(:func:`clfbev.supervision.targets.with_targets`), one projection for both.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.geometry import depth_bin_centres


def depth_loss(depth_probs: Tensor, targets: Tensor, depth_bins: tuple[float, float, float] | None = None,
               range_power: float = 0.0) -> Tensor:
    """BEVDepth's loss: BCE of the predicted distribution against the one-hot target bin,
    summed over bins, averaged over the cells with a target; with ``range_power`` p > 0 a
    weighted mean, each cell weighing (its target bin's depth)^p, the weights normalised to a
    mean of 1 (so the loss keeps its scale).

    Parameters
    ----------
    depth_probs : (B, N, D, h, w) softmax over D bins.
    targets : (B, N, h, w) int64 bin, -1 = no target.
    depth_bins : (d_min, d_max, d_step) of the bins (their centres give the weights); needed
        when ``range_power`` > 0.

    Returns
    -------
    () float32 loss (0 when no cell has a target).
    """
    D = depth_probs.shape[2]
    probs = depth_probs.permute(0, 1, 3, 4, 2).reshape(-1, D)
    t = targets.reshape(-1)
    fg = t >= 0
    # BCE on probabilities is not autocast-safe: always in float32.
    with torch.autocast(device_type=probs.device.type, enabled=False):
        p = probs[fg].float()
        onehot = F.one_hot(t[fg], D).float()
        if range_power > 0 and len(p):
            weight = depth_bin_centres(depth_bins).to(p.device)[t[fg]] ** range_power      # (n,)
            per_cell = F.binary_cross_entropy(p, onehot, reduction="none").sum(dim=1)
            total = (per_cell * (weight / weight.mean())).sum()
        else:
            total = F.binary_cross_entropy(p, onehot, reduction="sum")
    return total / max(1, int(fg.sum()))
