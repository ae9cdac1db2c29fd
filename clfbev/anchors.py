"""Class-specific anchors on the BEV grid and their matching thresholds (PointPillars / SECOND).

Every BEV cell carries, for each class, one anchor per rotation (0 and pi/2) with that class's
mean size. Anchors live in the lidar frame with the box convention of :mod:`clfbev.ops.boxes`:
``(x, y, z, l, w, h, yaw)``, ``z`` the box centre.

Layout
------
``make_anchors`` returns ``(ny, nx, n_cls, n_rot, 7)``: row ``iy`` of the BEV map is the y axis,
column ``ix`` the x axis, exactly like a ``(B, C, H=ny, W=nx)`` feature map (and like the voxel
grid ``(nz, ny, nx)`` of :mod:`clfbev.ops.voxelize`). Flattening with ``reshape(-1, 7)`` gives
the anchor order ``(iy, ix, cls, rot)`` that :mod:`clfbev.head` uses everywhere.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from clfbev.settings import ANCHOR_ROTATIONS, ANCHOR_SIZES

# The nuScenes LIDAR_TOP sits 1.84 m above the ego origin, which is on the ground, so the
# ground plane is at z = -1.84 in the lidar frame and an object standing on it has its centre
# at -1.84 + h / 2. This gives (metres, lidar frame):
#   car -0.98, truck -0.475, bus -0.105, trailer 0.07, construction_vehicle -0.275,
#   motorcycle -1.12, bicycle -1.205, pedestrian -0.96, traffic_cone -1.31, barrier -1.35.
# (mmdet3d's nuScenes PointPillars anchors put the box *bottoms* at -1.62 .. -1.81, i.e. the
# same ground within the spread of real boxes.) Anchors only need to be close: dz is regressed.
GROUND_Z_LIDAR = -1.84
ANCHOR_Z: dict[str, float] = {name: GROUND_Z_LIDAR + 0.5 * size[2] for name, size in ANCHOR_SIZES.items()}

# Per-class BEV-IoU matching thresholds (pos, neg): an anchor is positive when IoU >= pos,
# negative when IoU < neg, ignored in between. Values of SECOND's nuScenes multi-head config
# (also used by PointPillars ports): large rigid classes need tight overlap, small and thin
# classes (whose IoU drops fast with a small offset on the grid) get looser thresholds.
MATCH_THRESHOLDS: dict[str, tuple[float, float]] = {
    "car": (0.6, 0.45),
    "truck": (0.55, 0.4),
    "bus": (0.55, 0.4),
    "trailer": (0.5, 0.35),
    "construction_vehicle": (0.5, 0.35),
    "motorcycle": (0.5, 0.3),
    "bicycle": (0.5, 0.35),
    "pedestrian": (0.5, 0.35),
    "traffic_cone": (0.6, 0.4),
    "barrier": (0.55, 0.4),
}


def _check_classes(class_names: Sequence[str]) -> None:
    unknown = [name for name in class_names if name not in ANCHOR_SIZES]
    if unknown:
        raise ValueError(f"no anchor size for classes {unknown}; known: {sorted(ANCHOR_SIZES)}")


def match_thresholds(class_names: Sequence[str]) -> list[tuple[float, float]]:
    """``(pos, neg)`` IoU thresholds in the order of ``class_names`` (the order of the anchor
    class axis), as :func:`clfbev.supervision.assign.assign_targets` expects them."""
    _check_classes(class_names)
    return [MATCH_THRESHOLDS[name] for name in class_names]


def make_anchors(
    class_names: Sequence[str],
    feature_size: tuple[int, int],
    pc_range: Sequence[float],
    rotations: Sequence[float] = ANCHOR_ROTATIONS,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Anchors for every cell of a BEV feature map.

    Parameters
    ----------
    class_names : classes in the order of the head's class axis (e.g. :data:`clfbev.settings.DETECTION_CLASSES`).
    feature_size : ``(ny, nx)``, the height and width of the BEV feature map.
    pc_range : ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in metres, lidar frame; the map covers
        ``[xmin, xmax) x [ymin, ymax)``. The z limits are unused: anchor heights are per class.
    rotations : anchor headings in radians (default ``0, pi/2``).

    Returns
    -------
    (ny, nx, n_cls, n_rot, 7) anchors ``(x, y, z, l, w, h, yaw)``, lidar frame. Cell
    ``(iy, ix)`` is centred at ``x = xmin + (ix + 0.5) * (xmax - xmin) / nx`` and
    ``y = ymin + (iy + 0.5) * (ymax - ymin) / ny``.
    """
    _check_classes(class_names)
    if len(pc_range) != 6:
        raise ValueError(f"pc_range needs 6 values (xmin, ymin, zmin, xmax, ymax, zmax), got {pc_range}")
    ny, nx = feature_size
    xmin, ymin, _, xmax, ymax, _ = (float(v) for v in pc_range)
    n_cls, n_rot = len(class_names), len(rotations)

    # Cell centres, not corners: the feature at (iy, ix) summarises that cell's area.
    xs = xmin + (torch.arange(nx, device=device, dtype=torch.float64) + 0.5) * ((xmax - xmin) / nx)
    ys = ymin + (torch.arange(ny, device=device, dtype=torch.float64) + 0.5) * ((ymax - ymin) / ny)
    sizes = torch.tensor([ANCHOR_SIZES[name] for name in class_names], device=device, dtype=torch.float64)
    zs = torch.tensor([ANCHOR_Z[name] for name in class_names], device=device, dtype=torch.float64)
    yaws = torch.tensor(list(rotations), device=device, dtype=torch.float64)

    shape = (ny, nx, n_cls, n_rot)
    columns = [
        xs.view(1, nx, 1, 1).expand(shape),
        ys.view(ny, 1, 1, 1).expand(shape),
        zs.view(1, 1, n_cls, 1).expand(shape),
        sizes[:, 0].view(1, 1, n_cls, 1).expand(shape),
        sizes[:, 1].view(1, 1, n_cls, 1).expand(shape),
        sizes[:, 2].view(1, 1, n_cls, 1).expand(shape),
        yaws.view(1, 1, 1, n_rot).expand(shape),
    ]
    # Built in float64 so that centres far from the origin are exact before the final cast.
    return torch.stack(columns, dim=-1).to(dtype).contiguous()


def anchor_class_ids(anchors: Tensor) -> Tensor:
    """Class index (0-based, into ``class_names``) of each anchor.

    Parameters
    ----------
    anchors : (ny, nx, n_cls, n_rot, 7) from :func:`make_anchors`.

    Returns
    -------
    (ny * nx * n_cls * n_rot,) int64, in the flattened anchor order ``(iy, ix, cls, rot)``.
    """
    if anchors.dim() != 5 or anchors.shape[-1] != 7:
        raise ValueError(f"anchors must be (ny, nx, n_cls, n_rot, 7), got {tuple(anchors.shape)}")
    ny, nx, n_cls, n_rot, _ = anchors.shape
    ids = torch.arange(n_cls, device=anchors.device).view(1, 1, n_cls, 1)
    return ids.expand(ny, nx, n_cls, n_rot).reshape(-1)
