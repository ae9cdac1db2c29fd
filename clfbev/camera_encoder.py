"""Camera branch: ResNet + FPN + lift-splat (Philion & Fidler 2020) -> camera BEV.

Lift: every feature-map cell predicts a softmax over D depth bins and a context vector of C
channels; their outer product places the context along the cell's camera ray, weighted by the
depth probability. Splat: the D * h * w frustum points of every camera are summed into a
(nz, ny, nx) voxel grid over ``pc_range``; then the z slices are concatenated into channels.

Conventions
-----------
- Pixel coordinates are continuous with the pixel-edge convention: pixel (row r, col c) covers
  u in [c, c + 1), v in [r, r + 1), so its centre is (c + 0.5, r + 0.5). Then resizing an image by
  s scales K's first two rows by s exactly, and a horizontal flip of a W-wide image is u' = W - u.
  Feature cell (i, j) at stride s covers input pixels [j s, (j + 1) s) x [i s, (i + 1) s) and its
  frustum ray goes through the centre ((j + 0.5) s, (i + 0.5) s).
- ``img_aug`` (3, 3) maps ORIGINAL-image pixels (the ones ``intrinsics`` describe) to AUGMENTED
  pixels (the image the network sees): ``[u', v', 1]^T ~ img_aug @ [u, v, 1]^T``. It covers
  resize, crop, flip (and rotation). The geometry undoes it with ``img_aug^-1``.
- Camera frame: x right, y down, z forward; the depth of a bin is camera-frame z (not range).
- Depth bins ``(d_min, d_max, d_step)``: D = round((d_max - d_min) / d_step) bins; bin k covers
  [d_min + k step, d_min + (k + 1) step) and its frustum point sits at the bin centre, so the
  depth-bin target for a lidar depth z is ``floor((z - d_min) / step)``.
- Output frame: whatever ``T_lidar_from_cam`` maps to (the lidar frame). BEV cell (iy, ix) covers
  x in [xmin + ix dx, xmin + (ix + 1) dx), y in [ymin + iy dy, ...): rows index y, columns x.
- z-compression concatenates the nz slices into channels (as BEVFusion), which keeps height
  information; with nz = 1 (the usual camera grid, one 20 m slab) it equals a sum over z.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from clfbev.bilinear_lift import bilinear_lift
from clfbev.config import ModelConfig
from clfbev.efficientnet_lite import EfficientNetLite0
from clfbev.geometry import CameraGeometry, depth_bin_centres
from clfbev.resnet import FPN, ResNet
from clfbev.settings import grid_shape_of


def lift_geometry(cams: CameraGeometry) -> Tensor:
    """Lidar-frame position of every frustum point of the cameras ``cams``.

    Returns
    -------
    (B, N, D, h, w, 3) float32 lidar-frame xyz, h = H / stride, w = W / stride.
    """
    intrinsics, T_lidar_from_cam, img_aug = cams.intrinsics, cams.T_lidar_from_cam, cams.img_aug
    image_size, feature_stride, depth_bins = cams.image_size, cams.feature_stride, cams.depth_bins
    H, W = image_size
    s = feature_stride
    if H % s or W % s:
        raise ValueError(f"image_size {image_size} must be a multiple of feature_stride {s}")
    B, N = intrinsics.shape[:2]
    dev = intrinsics.device
    f32 = dict(device=dev, dtype=torch.float32)
    depths = depth_bin_centres(depth_bins).to(dev)                          # (D,)
    # Feature-cell centres in augmented-image pixels (pixel-edge convention).
    u = (torch.arange(W // s, **f32) + 0.5) * s
    v = (torch.arange(H // s, **f32) + 0.5) * s
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    pix = torch.stack([uu, vv, torch.ones_like(uu)], dim=-1)               # (h, w, 3)

    # Augmented pixel -> original pixel -> camera ray: ray ~ (A K)^-1 pix. In float64 so that
    # the round trip pixel -> ray -> pixel stays exact far below a pixel, whatever K's scale.
    K = intrinsics.double()
    M = K if img_aug is None else img_aug.double() @ K                     # cam ray -> aug pixel
    rays = torch.einsum("bnij,hwj->bnhwi", torch.linalg.inv(M), pix.double())
    # Normalise to z = 1 so that scaling by a bin depth gives camera z = that depth (also
    # absorbs any projective scale in img_aug).
    rays = rays / rays[..., 2:3]                                            # (B, N, h, w, 3)
    T = T_lidar_from_cam.double()
    R, t = T[..., :3, :3], T[..., :3, 3]
    # Rotate the unit-depth rays once, then scale by each bin depth: p = d R ray + t.
    rays_lidar = torch.einsum("bnij,bnhwj->bnhwi", R, rays).float()        # (B, N, h, w, 3)
    pts = depths.view(1, 1, -1, 1, 1, 1) * rays_lidar[:, :, None]           # (B, N, D, h, w, 3)
    return pts + t.float().view(B, N, 1, 1, 1, 3)


def splat(
    depth_probs: Tensor,
    context: Tensor,
    geometry: Tensor,
    pc_range: tuple[float, ...],
    bev_voxel: tuple[float, float, float],
) -> Tensor:
    """Sum the frustum features ``depth_probs (x) context`` into a voxel grid.

    Vectorised and without the (B, N, D, h, w, C) outer product (BEVPoolv2's idea, Huang and
    Huang 2022): voxel v gets ``sum over the points p in v of depth_probs[p] * context[cell(p)]``,
    a weighted sum of context rows, which ``F.embedding_bag`` computes per voxel (a bag) with
    ``per_sample_weights``, and differentiates in both. Points outside ``pc_range`` are dropped.
    It saves the memory of the outer product and the time of an ``index_add`` over it.

    Parameters
    ----------
    depth_probs : (B, N, D, h, w) weight of each frustum point (a softmax over D in the model).
    context : (B, N, C, h, w) per-cell context features.
    geometry : (B, N, D, h, w, 3) lidar-frame xyz of each frustum point (:func:`lift_geometry`).
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax), lidar frame, metres.
    bev_voxel : (dx, dy, dz) metres.

    Returns
    -------
    (B, C, nz, ny, nx) voxel features (a view of (B, nz, ny, nx, C) memory); voxel (iz, iy, ix)
    covers [min + i * d, min + (i + 1) * d) on each axis.
    """
    B, N, D, h, w = depth_probs.shape
    C = context.shape[2]
    if context.shape != (B, N, C, h, w) or geometry.shape != (B, N, D, h, w, 3):
        raise ValueError(
            f"splat: depth {tuple(depth_probs.shape)}, context {tuple(context.shape)} and geometry "
            f"{tuple(geometry.shape)} disagree; need (B,N,D,h,w), (B,N,C,h,w), (B,N,D,h,w,3)"
        )
    nz, ny, nx = grid_shape_of(pc_range, bev_voxel)
    n_cells = B * nz * ny * nx
    with torch.no_grad():       # where each point goes: integers of the geometry alone
        lo = geometry.new_tensor(pc_range[:3])
        size = geometry.new_tensor(bev_voxel)
        idx = torch.floor((geometry - lo) / size).long()                   # (B, N, D, h, w, 3) = ix, iy, iz
        ix, iy, iz = idx.unbind(-1)
        keep = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & (iz >= 0) & (iz < nz)
        b = torch.arange(B, device=geometry.device).view(B, 1, 1, 1, 1)
        voxel = (((b * nz + iz) * ny + iy) * nx + ix).flatten()            # (B N D h w,) voxel of every point
        # The kept points by their flat index into (B, N, D, h, w), found once (a boolean index
        # per array would search the mask each time), then in bag order: bags must be
        # contiguous, so by voxel (a stable sort, so the sums are reproducible).
        point = keep.flatten().nonzero().squeeze(1)                        # (P,)
        voxel, order = torch.sort(voxel[point], stable=True)
        point = point[order]
        # The context row of each point: its feature cell (b, n, i, j), whatever its depth bin.
        cell = point // (D * h * w) * (h * w) + point % (h * w)
        counts = torch.bincount(voxel, minlength=n_cells)
    rows = context.permute(0, 1, 3, 4, 2).reshape(B * N * h * w, C)
    out = F.embedding_bag(cell, rows, torch.cumsum(counts, 0) - counts, mode="sum",
                          per_sample_weights=depth_probs.flatten()[point])  # (n_cells, C)
    # (B, C, nz, ny, nx) as a view of the rows: channels-last memory, which the BEV backbone reads.
    return out.view(B, nz, ny, nx, C).permute(0, 4, 1, 2, 3)


def compress_z(voxels: Tensor) -> Tensor:
    """(B, C, nz, ny, nx) -> (B, nz * C, ny, nx): slice iz fills channels [iz C, (iz + 1) C)."""
    B, C, nz, ny, nx = voxels.shape
    return voxels.permute(0, 2, 1, 3, 4).reshape(B, nz * C, ny, nx)


class CameraEncoder(nn.Module):
    """Multi-camera images -> camera BEV by lift-splat.

    Parameters
    ----------
    depth, width : ResNet depth (18/34/50/101) and first-stage width.
    backbone : ``resnet`` (:class:`clfbev.resnet.ResNet` of ``depth`` and ``width``) or
        ``efficientnet_lite0`` (:class:`clfbev.efficientnet_lite.EfficientNetLite0`, for the
        ImageNet experiment; ``depth`` and ``width`` unused).
    fpn_ch : FPN output channels.
    depth_bins : (d_min, d_max, d_step) in metres of camera z.
    context_ch : C, context channels per frustum point.
    image_size : (H, W) of the (augmented) images fed to ``forward``.
    feature_stride : 8 (FPN over C3-C5) or 16 (FPN over C4-C5).
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) of the voxel grid, lidar frame.
    bev_voxel : (dx, dy, dz) voxel size.
    semantic_classes : when > 0, a 1x1 conv on the FPN features also predicts that many class
        logits per feature cell, for the perspective supervision (:mod:`clfbev.supervision.perspective`).
    semantic_lift : lift the class probabilities (sigmoid of those logits) with the context, as
        ``semantic_classes`` more channels per z slice, so that the camera BEV says what stands
        where and not only that something does (SA-BEV, Zhang et al. 2023, lifts image
        semantics in the same spirit). Needs ``semantic_classes > 0``.
    prior_prob : the initial class probability of the semantic head (the focal-loss prior).
    lift : ``splat`` (the depth bins above) or ``bilinear`` (each BEV cell samples the context
        where its column of points at the heights ``lift_heights`` (lidar z, m) projects,
        :mod:`clfbev.bilinear_lift`; the depth distribution is still predicted, for the depth
        loss, but lifts nothing).
    """

    def __init__(
        self,
        depth: int,
        width: int,
        fpn_ch: int,
        depth_bins: tuple[float, float, float],
        context_ch: int,
        image_size: tuple[int, int],
        feature_stride: int,
        pc_range: tuple[float, ...],
        bev_voxel: tuple[float, float, float],
        semantic_classes: int = 0,
        semantic_lift: bool = False,
        prior_prob: float = 0.01,
        backbone: str = "resnet",
        lift: str = "splat",
        lift_heights: tuple[float, ...] = (-1.4, -0.6),
    ) -> None:
        super().__init__()
        self.lift, self.lift_heights = lift, tuple(float(z) for z in lift_heights)
        if semantic_lift and semantic_classes < 1:
            raise ValueError("semantic_lift needs semantic_classes > 0")
        self.semantic_lift = semantic_lift
        self.image_features_frozen = False
        if feature_stride not in (8, 16):
            raise ValueError(f"feature_stride must be 8 or 16, got {feature_stride}")
        self.depth_bins = tuple(float(v) for v in depth_bins)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.feature_stride = feature_stride
        self.pc_range = tuple(float(v) for v in pc_range)
        self.bev_voxel = tuple(float(v) for v in bev_voxel)
        self.grid_shape = grid_shape_of(self.pc_range, self.bev_voxel)      # (nz, ny, nx)
        self.num_depth_bins = len(depth_bin_centres(self.depth_bins))
        self.context_ch = context_ch
        self.lifted_ch = context_ch + (semantic_classes if semantic_lift else 0)
        H, W = self.image_size
        if H % feature_stride or W % feature_stride:
            raise ValueError(f"image_size {image_size} must be a multiple of feature_stride {feature_stride}")

        self.backbone = EfficientNetLite0() if backbone == "efficientnet_lite0" else ResNet(depth, 3, width)
        # Levels fed to the FPN: its output has the stride of the finest one.
        self._levels = slice(0, 3) if feature_stride == 8 else slice(1, 3)
        self.neck = FPN(list(self.backbone.out_channels[self._levels]), fpn_ch)
        # One 1x1 conv predicts D depth logits and C context channels per cell (LSS).
        self.depth_net = nn.Conv2d(fpn_ch, self.num_depth_bins + context_ch, 1)
        self.semantic_head: nn.Conv2d | None = None
        if semantic_classes > 0:
            self.semantic_head = nn.Conv2d(fpn_ch, semantic_classes, 1)
            # The focal-loss prior (as the anchor head): every class starts at probability prior_prob.
            nn.init.constant_(self.semantic_head.bias, -math.log((1 - prior_prob) / prior_prob))
        self.to(memory_format=torch.channels_last)

    @classmethod
    def from_config(cls, cfg: ModelConfig) -> CameraEncoder:
        """The camera encoder of a detector of ``cfg`` (the detector's and the image-view
        pretraining's: one state dict layout)."""
        return cls(cfg.cam_depth, cfg.cam_width, cfg.fpn_ch, cfg.depth_bins, cfg.context_ch,
                   cfg.image_size, cfg.feature_stride, cfg.pc_range, cfg.cam_bev_voxel,
                   semantic_classes=len(cfg.class_names) if cfg.loss.semantic > 0 else 0,
                   semantic_lift=cfg.cam_semantic_lift, prior_prob=cfg.prior_prob, backbone=cfg.cam_backbone,
                   lift=cfg.cam_lift, lift_heights=cfg.cam_lift_heights)

    def freeze_image_features(self) -> None:
        """Keep the ResNet and the FPN as they are (the pretrained image features): no gradient,
        and their BatchNorm stays in eval mode with its statistics, in training too. The depth
        net (depth bins and context) and the semantic head still train. Their backward pass,
        the larger part of the encoder's cost, is then never computed."""
        for module in (self.backbone, self.neck):
            module.requires_grad_(False)
        self.image_features_frozen = True
        self.train(self.training)

    def train(self, mode: bool = True) -> CameraEncoder:
        super().train(mode)
        if self.image_features_frozen:
            self.backbone.eval()
            self.neck.eval()
        return self

    @property
    def out_channels(self) -> int:
        """Channels of the camera BEV: the lifted channels (the context, and the class
        probabilities with ``semantic_lift``) per z slice."""
        return self.lifted_ch * self.grid_shape[0]

    @property
    def bev_shape(self) -> tuple[int, int]:
        """(ny, nx) of the camera BEV."""
        return self.grid_shape[1], self.grid_shape[2]

    def fpn_features(self, images: Tensor) -> Tensor:
        """images (B, N, 3, H, W) -> FPN features (B * N, fpn_ch, H / stride, W / stride): what the
        depth net and the heads of the image-view pretraining (:mod:`clfbev.run.pretrain`) read."""
        H, W = images.shape[-2:]
        if (H, W) != self.image_size:
            raise ValueError(f"CameraEncoder built for image_size {self.image_size}, got {(H, W)}")
        # Channels-last: the CPU's oneDNN convolutions and cuDNN under AMP are faster in it.
        feats = self.backbone(images.flatten(0, 1).contiguous(memory_format=torch.channels_last))
        return self.neck(feats[self._levels])

    def image_features(self, images: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """images (B, N, 3, H, W) -> depth_probs (B, N, D, h, w), context (B, N, C, h, w) and the
        class logits (B, N, semantic_classes, h, w), or None without a semantic head.

        Exposed separately so a caller can supervise the depth distribution (BEVDepth-style) and
        the classes (:mod:`clfbev.supervision.perspective`).
        """
        return self.heads(self.fpn_features(images).unflatten(0, images.shape[:2]))

    def heads(self, fpn: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """FPN features (B, N, fpn_ch, h, w) -> depth_probs, context and class logits as
        :meth:`image_features` gives them: what reads the image features after the (frozen)
        ResNet and FPN, so a cache of those features (:mod:`clfbev.feature_cache`) can feed it."""
        B, N, _, h, w = fpn.shape
        fpn = fpn.flatten(0, 1)
        x = self.depth_net(fpn).contiguous()
        D = self.num_depth_bins
        depth = x[:, :D].softmax(dim=1).view(B, N, D, h, w)
        context = x[:, D:].reshape(B, N, self.context_ch, h, w)
        semantics = None
        if self.semantic_head is not None:
            semantics = self.semantic_head(fpn).contiguous().view(B, N, -1, h, w)
        return depth, context, semantics

    def forward(
        self,
        images: Tensor,
        intrinsics: Tensor,
        T_lidar_from_cam: Tensor,
        img_aug: Tensor | None = None,
    ) -> Tensor:
        """Camera BEV, (B, out_channels, ny, nx); see :meth:`lift_splat`."""
        return self.lift_splat(images, intrinsics, T_lidar_from_cam, img_aug)[0]

    def lift_splat(
        self,
        images: Tensor,
        intrinsics: Tensor,
        T_lidar_from_cam: Tensor,
        img_aug: Tensor | None = None,
        oracle_bins: Tensor | None = None,
        fpn: Tensor | None = None,
        missing: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """Camera BEV, the depth distribution it was lifted with (for the depth loss) and the
        class logits of the image features (for the perspective loss).

        Parameters
        ----------
        images : (B, N, 3, H, W) normalised images (after augmentation).
        intrinsics : (B, N, 3, 3) K of the original images.
        T_lidar_from_cam : (B, N, 4, 4) camera -> lidar frame.
        img_aug : (B, N, 3, 3) original -> augmented pixels, or None.
        oracle_bins : (B, N, h, w) int64 depth bin to lift each cell with in place of its
            predicted distribution (one-hot), -1 to keep the prediction; None: the prediction
            everywhere. A diagnostic (:func:`oracle_depth`), not a model.
        fpn : (B, N, fpn_ch, h, w) the frozen ResNet's and FPN's features of ``images``, cached
            (:mod:`clfbev.feature_cache`), read in place of running them; ``images`` is then
            unused. Only with the image features frozen: trained ones would leave a cache stale.
        missing : (B, N) bool the cameras that delivered nothing, or None: nothing is lifted from
            them (their context features are zeroed before the lift).

        Returns
        -------
        bev : (B, out_channels, ny, nx) camera BEV in the lidar frame.
        depth : (B, N, D, h, w) the PREDICTED depth distribution of every feature cell.
        semantics : (B, N, semantic_classes, h, w) class logits, or None without a semantic head.
        """
        if fpn is None:
            depth, context, semantics = self.image_features(images)
        elif not self.image_features_frozen:
            raise ValueError("cached FPN features need the image features frozen (freeze_image_features)")
        else:
            depth, context, semantics = self.heads(fpn)
        if self.semantic_lift:
            context = torch.cat([context, semantics.sigmoid()], dim=2)           # (B, N, C + n_cls, h, w)
        if missing is not None:
            context = context * ~missing[:, :, None, None, None]
        cams = CameraGeometry(intrinsics, T_lidar_from_cam, img_aug, self.image_size, self.feature_stride,
                              self.depth_bins)
        if self.lift == "bilinear":
            return bilinear_lift(context, cams, self.pc_range, self.bev_voxel, self.lift_heights), depth, semantics
        geom = lift_geometry(cams)
        lifted = depth if oracle_bins is None else oracle_depth(depth, oracle_bins)
        return compress_z(splat(lifted, context, geom, self.pc_range, self.bev_voxel)), depth, semantics


def oracle_depth(depth_probs: Tensor, bins: Tensor) -> Tensor:
    """The depth distribution with the cells that have a known bin made one-hot at it.

    An oracle lift: with the lidar's depth in place of the predicted one, what the camera BEV
    still lacks is recognition, so a camera-only detector trained so separates the depth error
    from the image features' (a diagnostic; the lidar is not a camera's input).

    depth_probs : (B, N, D, h, w); bins : (B, N, h, w) int64, -1 where unknown -> (B, N, D, h, w).
    """
    D = depth_probs.shape[2]
    known = bins >= 0
    onehot = F.one_hot(bins.clamp(min=0), D).permute(0, 1, 4, 2, 3).to(depth_probs.dtype)
    return torch.where(known[:, :, None], onehot, depth_probs)
