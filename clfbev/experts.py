"""A fused detector that keeps a camera-only and a lidar-only expert beside it, and answers
each sample with the expert whose sensors delivered.

MoME (Park et al., CVPR 2024) decodes with three parallel experts, camera, lidar and fused, and
lets a learned router pick one per object query by the quality of each sensor's features; with
the lidar dropped out it keeps 0.65 of its clean NDS, where a fused decoder alone collapses. This
is its simplest form, the staged recipe's three models as the experts and the router a rule on
what the sample says it received:

- the lidar delivered no point at all (``Batch.points`` empty: a lost or unplugged lidar), and
  some camera did -> the camera expert;
- every camera is marked missing (``Batch.camera_missing`` all True) and the lidar delivered ->
  the lidar expert;
- else (both sensors, or a degraded one that still delivers: fewer beams, one camera lost, fog)
  -> the fused model.

A sensor that delivers garbage rather than nothing is the fused model's to handle (and the
learned router's, not built here). Each expert is a whole trained :class:`clfbev.model.CLFusionBEV`
of the same classes and loader settings (one batch feeds all three); an expert absent falls back
to the fused model.
"""

from __future__ import annotations

from torch import Tensor, nn

from clfbev.data import Batch
from clfbev.errors import ConfigError
from clfbev.head import Detections
from clfbev.model import CLFusionBEV

FUSED, CAMERA, LIDAR = "fused", "camera", "lidar"
ROLES = (FUSED, CAMERA, LIDAR)


def route(batch: Batch) -> list[str]:
    """One of :data:`ROLES` per sample of ``batch``, by the rule of the module docstring."""
    routes = []
    for i, points in enumerate(batch.points):
        lidar_lost = points.shape[0] == 0
        cameras_lost = batch.camera_missing is not None and bool(batch.camera_missing[i].all())
        if lidar_lost and not cameras_lost:
            routes.append(CAMERA)
        elif cameras_lost and not lidar_lost:
            routes.append(LIDAR)
        else:
            routes.append(FUSED)
    return routes


class SensorExperts(nn.Module):
    """The fused model with its per-sensor experts; :meth:`predict` as
    :meth:`clfbev.model.CLFusionBEV.predict`, each sample by its routed expert.

    ``cfg`` is the fused model's (the loader's settings and the classes, which every expert
    shares); ``variant`` reads ``<fused variant>+experts``.
    """

    def __init__(self, fused: CLFusionBEV, camera: CLFusionBEV | None = None,
                 lidar: CLFusionBEV | None = None) -> None:
        super().__init__()
        check_experts(fused, camera, lidar)
        self.fused, self.camera, self.lidar = fused, camera, lidar
        self.cfg = fused.cfg
        self.variant = f"{fused.variant}+experts"

    def expert(self, role: str) -> CLFusionBEV:
        """The model that answers samples routed to ``role`` (the fused one where that expert is absent)."""
        model = getattr(self, role)
        return self.fused if model is None else model

    def predict(self, batch: Batch, **decode_options) -> list[Detections]:
        """B Detections (lidar frame), sample i's from the expert :func:`route` picks for it;
        ``decode_options`` as :meth:`clfbev.model.CLFusionBEV.predict` takes them."""
        routes = route(batch)
        out: list[Detections | None] = [None] * len(routes)
        for role in ROLES:
            index = [i for i, r in enumerate(routes) if r == role]
            if not index:
                continue
            dets = self.expert(role).predict(batch.select(index), **decode_options)
            for i, d in zip(index, dets):
                out[i] = d
        return out

    def forward(self, batch: Batch) -> Tensor:
        raise TypeError("SensorExperts answers through predict(); each expert's forward is its own")


def check_experts(fused: CLFusionBEV, camera: CLFusionBEV | None, lidar: CLFusionBEV | None) -> None:
    """Refuse (ConfigError) experts that cannot answer one batch together: a fused model that is
    not of a fused variant, a camera expert not of variant ``camera`` or a lidar expert not
    ``lidar``, other classes or loader settings than the fused model's, or an oracle lift (it
    reads the lidar's depth, which a camera expert must not need)."""
    if fused.variant not in ("concat", "mcm", "full"):
        raise ConfigError(f"the fused expert is of variant '{fused.variant}', not a fused one (concat, mcm, full)")
    for role, model, want in ((CAMERA, camera, "camera"), (LIDAR, lidar, "lidar")):
        if model is None:
            continue
        if model.variant != want:
            raise ConfigError(f"the {role} expert is of variant '{model.variant}', not '{want}'")
        if model.cfg.data_config() != fused.cfg.data_config():
            raise ConfigError(f"the {role} expert reads other data than the fused model (classes, image size, "
                              f"sweeps or point range): {model.cfg.data_config()} != {fused.cfg.data_config()}")
    for role, model in ((FUSED, fused), (CAMERA, camera), (LIDAR, lidar)):
        if model is not None and model.cfg.cam_oracle_depth:
            raise ConfigError(f"the {role} expert lifts with the lidar's depth (cam_oracle_depth), a measurement "
                              "tool, not an expert")
