"""CL-FusionBEV end to end on a synthetic batch (no simgen): every variant trains one step, the
unused modality is absent, derived config sizes match the real shapes, YAML overrides are strict.

The batch: B = 1, six cameras at the lidar origin looking out horizontally every 60 degrees
(nuScenes camera axes: x right, y down, z forward), nuScenes-like K of a 1600 x 900 image
resized to the network's image size, ~5000 lidar-like points (a ground plane at z = -1.84 plus
points on the three GT boxes: a car, a pedestrian and a bicycle).

The training step's speed is measured by ``scripts/bench.py`` (``train_tiny_samples_per_s``),
not asserted here: a shared machine's timings are noise to a test. The paper forward (6 x 640 x
1600 images, 30k points) is marked slow.
"""

import math
import pickle
import resource
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

from clfbev.config import VARIANTS, paper, tiny
from clfbev.config_file import load_config
from clfbev.data import Batch, NuScenesDetection
from clfbev.errors import ConfigError
from clfbev.lidar_encoder import SparseEncoder
from clfbev.model import CLFusionBEV, count_parameters
from clfbev.run.attention_query import attention_maps
from clfbev.supervision.targets import TrainingCollate, batch_loss, build_targets, training_loss

pytestmark = pytest.mark.usefixtures("one_thread")

CLASSES = ("car", "pedestrian", "bicycle")



def camera_rig(n_cams: int = 6) -> torch.Tensor:
    """(N, 4, 4) T_lidar_from_cam: cameras at the origin, headings 0, 60, ... degrees."""
    Ts = []
    for i in range(n_cams):
        yaw = 2 * math.pi * i / n_cams
        c, s = math.cos(yaw), math.sin(yaw)
        T = torch.eye(4)
        T[:3, 0] = torch.tensor([s, -c, 0.0])   # camera x (right) in lidar axes
        T[:3, 1] = torch.tensor([0.0, 0.0, -1.0])  # camera y (down)
        T[:3, 2] = torch.tensor([c, s, 0.0])    # camera z (forward, the viewing direction)
        T[:3, 3] = torch.tensor([0.0, 0.0, 0.0])
        Ts.append(T)
    return torch.stack(Ts)


def make_batch(cfg, n_points: int = 5000, seed: int = 0) -> Batch:
    """A B = 1 batch shaped like clfbev.data.Batch, geometry in the lidar frame."""
    g = torch.Generator().manual_seed(seed)
    H, W = cfg.image_size
    K = torch.tensor([[1266.0, 0.0, 800.0], [0.0, 1266.0, 450.0], [0.0, 0.0, 1.0]])  # original 1600 x 900
    A = torch.diag(torch.tensor([W / 1600, H / 900, 1.0]))                         # original -> resized
    labels = torch.tensor([cfg.class_names.index(c) for c in CLASSES])
    boxes = torch.tensor([  # x, y, z, l, w, h, yaw, vx, vy
        [12.0, 4.0, -0.98, 4.6, 1.9, 1.7, 0.3, 2.0, 0.5],
        [6.0, -3.0, -0.96, 0.7, 0.7, 1.8, 1.2, 0.0, 0.0],
        [-9.0, 11.0, -1.2, 1.7, 0.6, 1.3, -2.0, 1.0, 0.0],
    ])
    # Lidar-like points: ground plane over the range, plus points inside each box.
    lo, hi = torch.tensor(cfg.pc_range[:2]), torch.tensor(cfg.pc_range[3:5])
    n_obj = 300
    n_ground = n_points - n_obj * len(boxes)
    ground = torch.cat([lo + (hi - lo) * torch.rand(n_ground, 2, generator=g),
                        -1.84 + 0.05 * torch.randn(n_ground, 1, generator=g)], 1)
    objs = []
    for b in boxes:
        local = (torch.rand(n_obj, 3, generator=g) - 0.5) * b[3:6]
        c, s = math.cos(b[6]), math.sin(b[6])
        R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        objs.append(local @ R.T + b[:3])
    xyz = torch.cat([ground, *objs])
    points = torch.cat([xyz, torch.rand(len(xyz), 1, generator=g), torch.zeros(len(xyz), 1)], 1)
    return Batch(
        images=torch.randn(1, 6, 3, H, W, generator=g),
        intrinsics=K.expand(1, 6, 3, 3).clone(),
        T_lidar_from_cam=camera_rig()[None],
        img_aug=A.expand(1, 6, 3, 3).clone(),
        points=[points],
        gt_boxes=[boxes],
        gt_labels=[labels],
        T_global_from_lidar=torch.eye(4, dtype=torch.float64)[None],
        sample_tokens=["synthetic"],
    )


def train_step(model, batch, opt):
    losses = batch_loss(model, batch)
    opt.zero_grad()
    losses["loss"].backward()
    opt.step()
    return losses


@pytest.mark.parametrize("variant", VARIANTS)
def test_variant_trains_and_predicts(variant):
    torch.manual_seed(0)
    cfg = tiny()
    model = CLFusionBEV(cfg, variant)
    batch = make_batch(cfg)
    names = [n for n, _ in model.named_parameters()]
    # The unused modality is not built at all (so it can never run).
    assert (model.camera_encoder is None) == (variant == "lidar")
    assert (model.lidar_encoder is None) == (variant == "camera")
    if variant == "lidar":
        assert not any(n.startswith("camera_encoder") for n in names)
    if variant == "camera":
        assert not any(n.startswith("lidar_encoder") for n in names)
    assert (model.mcm is not None) == (variant in ("mcm", "full"))
    assert (model.bsm is not None) == (variant == "full")
    assert (model.fuser is not None) == (variant in ("concat", "mcm", "full"))

    opt = torch.optim.AdamW(model.parameters(), lr=2e-4, weight_decay=1e-2)
    losses = batch_loss(model, batch)
    opt.zero_grad()
    losses["loss"].backward()
    assert torch.isfinite(losses["loss"])
    assert losses["num_pos"] >= 3          # every GT forces at least one positive anchor
    missing = [n for n, p in model.named_parameters() if p.grad is None]
    assert not missing, f"no gradient: {missing[:5]}"
    bad = [n for n, p in model.named_parameters() if not torch.isfinite(p.grad).all()]
    assert not bad, f"non-finite gradient: {bad[:5]}"
    # The branch outputs matter: the encoders' first layers get a non-zero gradient.
    if model.lidar_encoder is not None:
        assert model.lidar_encoder.vfe.point_mlp[0].weight.grad.abs().sum() > 0
    if model.camera_encoder is not None:
        assert model.camera_encoder.backbone.stem[0].weight.grad.abs().sum() > 0
    before = [p.detach().clone() for p in model.parameters()]
    opt.step()
    assert any(not torch.equal(a, p) for a, p in zip(before, model.parameters()))

    model.eval()
    dets = model.predict(batch, score_thr=0.0, max_per_sample=50)
    assert len(dets) == 1
    assert dets[0].boxes.shape[1] == 9 and dets[0].boxes.ndim == 2
    assert 0 < len(dets[0].boxes) <= 50
    assert dets[0].scores.shape == dets[0].labels.shape == (len(dets[0].boxes),)
    assert torch.isfinite(dets[0].boxes).all()


@pytest.mark.parametrize("variant", VARIANTS)
def test_derived_sizes_match_real_shapes(variant):
    cfg = tiny()
    model = CLFusionBEV(cfg, variant).eval()
    batch = make_batch(cfg)
    ny, nx = cfg.head_feature_size
    with torch.no_grad():
        if model.lidar_encoder is not None:
            lidar_bev = model.lidar_encoder(batch.points)
            assert lidar_bev.shape == (1, cfg.lidar_bev_channels, *cfg.lidar_bev_shape)
            assert model.lidar_encoder.grid_shape == cfg.lidar_grid_shape
        if model.camera_encoder is not None:
            cam_bev = model.camera_encoder(batch.images, batch.intrinsics, batch.T_lidar_from_cam, batch.img_aug)
            assert cam_bev.shape == (1, cfg.cam_bev_channels, *cfg.cam_bev_shape)
        bev = model.bev_features(batch)
        assert bev.shape == (1, cfg.bev_channels_of(variant), ny, nx)
        feats = model.backbone(bev)
        assert feats.shape == (1, cfg.head_in_channels, ny, nx)
        out = model(batch).head
    A = len(cfg.class_names) * len(cfg.anchor_rotations)
    assert out.cls_logits.shape == (1, A, ny, nx)
    assert out.box_deltas.shape == (1, A * cfg.code_size, ny, nx)
    assert model.anchors.shape == (ny, nx, len(cfg.class_names), len(cfg.anchor_rotations), 7)
    assert "anchors" not in model.state_dict()   # derived, not saved


@pytest.mark.parametrize("variant", ["lidar", "camera", "full"])
def test_velocity_tower_trains_and_reads_the_sweep_bands(variant):
    """A tower model trains and predicts; with a lidar it is given the sweep bands, the last
    channels of the lidar BEV (the camera variant has none)."""
    cfg = replace(tiny(), velocity_tower=8)
    model = CLFusionBEV(cfg, variant)
    assert model.motion_ch == (0 if variant == "camera" else cfg.sweep_channels)
    assert model.head.velocity.reduce[0].in_channels == cfg.head_in_channels + model.motion_ch
    batch = make_batch(cfg)
    opt = torch.optim.SGD(model.parameters(), lr=1e-3)
    losses = train_step(model, batch, opt)
    assert torch.isfinite(losses["loss"]) and losses["loss_vel"] >= 0
    model.eval()
    dets = model.predict(batch, score_thr=0.0, max_per_sample=10)
    assert dets[0].boxes.shape[1] == 9 and torch.isfinite(dets[0].boxes).all()


def test_camera_bev_matches_lidar_bev_for_presets():
    for cfg in (tiny(), paper(), replace(tiny(), voxel_size=(0.2, 0.4, 0.4), sparse_channels=(16, 32))):
        assert cfg.cam_bev_shape == cfg.lidar_bev_shape
    assert tiny().lidar_bev_shape == (128, 128) and tiny().cam_bev_voxel[:2] == (0.8, 0.8)
    assert paper().lidar_bev_shape == (180, 180) and paper().lidar_grid_shape == (40, 1440, 1440)


@pytest.mark.parametrize("variant", ["concat", "mcm", "full"])
def test_fused_bev_is_the_lidar_path_at_initialisation(variant):
    """Whatever the camera BEV holds, the fused BEV of a fresh model is exactly
    ReLU(BN(conv_lidar(F_lidar))): MCM and BSM pass through (MCM its first fusion_dim channels:
    the sweep bands after them enter with weight 0), the fuser's camera weights are 0."""
    cfg = tiny()
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, variant).eval()
    g = torch.Generator().manual_seed(1)
    lidar = torch.relu(torch.randn(2, cfg.lidar_bev_channels, *cfg.lidar_bev_shape, generator=g))
    cams = [torch.randn(2, cfg.cam_bev_channels, *cfg.cam_bev_shape, generator=g) * s for s in (1.0, 30.0)]
    with torch.no_grad():
        fused = [model.fuse(lidar, cam)[0] for cam in cams]
        f = model.fuser
        expected = f.act(f.bn(f.conv_lidar(lidar if variant == "concat" else lidar[:, : cfg.fusion_dim])))
    assert cfg.lidar_bev_channels > cfg.fusion_dim        # the sparse channels and the sweep bands
    assert torch.equal(fused[0], fused[1])
    assert torch.equal(fused[0], expected)


def test_load_config(tmp_path):
    assert load_config("tiny") == tiny() and load_config("paper") == paper()
    bad = tmp_path / "bad.yaml"
    cases = {
        "fusion_dim: 32\nfusoin_heads: 4\n": r"bad\.yaml.*unknown key 'fusoin_heads'",
        "loss:\n  clss: 2.0\n": r"bad\.yaml.*unknown key 'loss\.clss'",
        "fusion_dim: wide\n": r"bad\.yaml.*'fusion_dim'",
        "attn_mode: global\n": r"bad\.yaml.*attn_mode",
        "attn_ffn_ratio: .nan\n": r"bad\.yaml: key 'attn_ffn_ratio' must be a finite number",
        "depth_bins: [1.0, .inf, 1.0]\n": r"bad\.yaml: key 'depth_bins' must be a list of finite values",
        "loss: {depth: -.inf}\n": r"bad\.yaml: key 'loss\.depth' must be a finite number",
        "voxel_size: [0.0, 0.4, 0.4]\n": r"bad\.yaml: voxel_size must be > 0",
        "voxel_size: [300.0, 0.4, 0.4]\n": r"bad\.yaml: .*empty voxel grid",
        "sweep_bands: 0\nsweep_offsets: true\n": r"bad\.yaml: sweep_offsets and sweep_trail need sweep_bands > 0",
        "heading_follow_classes: [walker]\n": r"bad\.yaml: heading_follow_classes \[.walker.\] are not in class_names",
        "image_size: [192, 352\nfusion_dim: 8\n": r"bad\.yaml: not valid YAML at line \d+, column \d+",
        "- 1\n- 2\n": r"bad\.yaml: expected a mapping",
    }
    for text, message in cases.items():
        bad.write_text(text)
        with pytest.raises(ConfigError, match=message) as e:
            load_config(bad)
        assert "\n" not in str(e.value), text                 # one line, no parser caret block
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "missing.yaml")
    good = tmp_path / "good.yaml"
    good.write_text("preset: paper\nattn_mode: window\nimage_size: [256, 704]\nloss: {cls: 2}\n")
    cfg = load_config(good)
    assert cfg == replace(paper(), attn_mode="window", image_size=(256, 704),
                          loss=replace(paper().loss, cls=2.0))


def test_config_is_a_leaf():
    """clfbev.config imports no model module and no torch (it builds nothing to learn its sizes)."""
    code = "import sys, clfbev.config; print(sorted(m for m in sys.modules if m.startswith(('clfbev', 'torch'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert eval(out) == ["clfbev", "clfbev.config", "clfbev.errors", "clfbev.settings"]


ODD_CONFIGS = [replace(tiny(), voxel_size=(0.2, 0.4, 0.4), sparse_channels=(16, 32)),
               replace(tiny(), lidar_bev_stride=1, sparse_channels=(8, 16, 32, 32), pc_range=(-50, -50, -3, 50, 50, 3),
                       voxel_size=(0.8, 0.8, 0.3)),
               replace(paper(), lidar_bev_stride=4, voxel_size=(0.15, 0.15, 0.2))]


@pytest.mark.parametrize("cfg", [tiny(), paper(), *ODD_CONFIGS], ids=["tiny", "paper", "odd1", "odd2", "odd3"])
def test_derived_sizes_equal_the_modules_own(cfg):
    """The config's arithmetic gives what the modules built from it compute, for every variant."""
    with torch.device("meta"):   # no memory, no init cost
        sparse = SparseEncoder(cfg.vfe_ch, cfg.sparse_channels, cfg.lidar_grid_shape, cfg.sparse_blocks,
                               xy_stride=cfg.lidar_bev_stride)
        assert (sparse.out_size(), sparse.out_channels + cfg.sweep_channels) == (cfg.lidar_bev_shape,
                                                                                  cfg.lidar_bev_channels)
        for variant in VARIANTS:
            model = CLFusionBEV(cfg, variant)
            if model.lidar_encoder is not None:
                assert model.lidar_encoder.out_channels == cfg.lidar_bev_channels
                assert model.lidar_encoder.out_size == cfg.lidar_bev_shape
            if model.camera_encoder is not None:
                assert model.camera_encoder.out_channels == cfg.cam_bev_channels
                assert model.camera_encoder.bev_shape == cfg.cam_bev_shape == cfg.lidar_bev_shape
            assert model.backbone.stages[0][0].in_channels == cfg.bev_channels_of(variant)
            assert model.head.conv_cls.in_channels == cfg.head_in_channels


@pytest.mark.parametrize("variant", ["mcm", "full"])
def test_forward_exposes_the_attention_inputs(variant):
    """The attention maps drawn from the forward's own inputs equal those of re-running the
    encoders up to each module (the attention picture's former path)."""
    torch.manual_seed(0)
    cfg = tiny()
    model = CLFusionBEV(cfg, variant).eval()
    for p in list(model.mcm.parameters()) + ([] if model.bsm is None else list(model.bsm.parameters())):
        p.data.normal_(0, 0.2, generator=torch.Generator().manual_seed(3))   # open the gates
    batch = make_batch(cfg)
    cell = (70, 75)
    with torch.no_grad():
        att = model(batch).attention
        lidar_bev = model.lidar_encoder(batch.points)
        cam_bev = model.camera_encoder(batch.images, batch.intrinsics, batch.T_lidar_from_cam, batch.img_aug)
        rerun = [model.mcm.attention_map(lidar_bev, cam_bev, cell)]
        if model.bsm is not None:
            rerun.append(model.bsm.attention_map(model.fuser(model.mcm(lidar_bev, cam_bev), cam_bev), cell))
        exposed = [model.mcm.attention_map(att.mcm_lidar, att.mcm_camera, cell)]
        if model.bsm is not None:
            exposed.append(model.bsm.attention_map(att.bsm, cell))
        else:
            assert att.bsm is None
    for a, b in zip(exposed, rerun):
        assert torch.equal(a, b) and a.shape == (1, cfg.attn_heads, *cfg.lidar_bev_shape)
        assert a.sum(dim=(2, 3)).sub(1).abs().max() < 1e-5 and a.std() > 0
    # ... and those the attention picture draws today.
    drawn = attention_maps(model, batch, cell)
    assert [m.name for m in drawn] == ["MCM", "BSM"][: len(exposed)]
    for a, m in zip(exposed, drawn):
        assert np.array_equal(a[0].numpy(), m.weights)


@pytest.mark.parametrize("variant", ["lidar", "full"])
def test_training_collate_builds_the_targets_model_loss_uses(tiny_dataset, variant):
    cfg = replace(tiny(), loss=replace(tiny().loss, semantic=1.0))
    ds = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-train", cfg.data_config())
    collate_fn = pickle.loads(pickle.dumps(TrainingCollate(cfg, cameras=variant != "lidar")))   # as to a worker
    batch, targets = collate_fn([ds[0], ds[1]])
    assert targets.anchor.labels.shape == (2, math.prod(cfg.head_feature_size) * 20)
    assert (targets.depth is None) == (targets.semantic is None) == (variant == "lidar")
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, variant)
    assert torch.equal(collate_fn.anchors, model.anchors)
    again = build_targets(batch, cfg, model.anchors, cameras=variant != "lidar")
    assert all(torch.equal(getattr(targets.anchor, f), getattr(again.anchor, f)) for f in ("labels", "box_targets"))
    if variant != "lidar":
        assert torch.equal(targets.depth, again.depth) and (targets.depth >= 0).sum() > 100
        assert torch.equal(targets.semantic, again.semantic) and (targets.semantic < 10).any()
    torch.manual_seed(1)
    outside = training_loss(model(batch), targets.to("cpu"), cfg)
    torch.manual_seed(1)
    inside = batch_loss(model, batch)
    assert outside.keys() == inside.keys() and all(torch.equal(outside[k], inside[k]) for k in inside)
    assert ("loss_depth" in inside) == ("loss_semantic" in inside) == (variant != "lidar")


def test_to_dict_round_trip(tmp_path):
    import yaml
    for cfg in (tiny(), paper()):
        path = tmp_path / "run.yaml"
        path.write_text(yaml.safe_dump(cfg.to_dict()))
        assert load_config(path) == cfg


def test_parameter_counts():
    n_tiny = count_parameters(CLFusionBEV(tiny(), "full"))
    with torch.device("meta"):   # no memory for the big one
        n_paper = count_parameters(CLFusionBEV(paper(), "full"))
    print(f"\nparameters: tiny full {n_tiny:,}, paper full {n_paper:,}")
    assert n_tiny < 5e6 < n_paper


@pytest.mark.slow
def test_paper_forward_on_cpu():
    cfg = paper()
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "full").eval()
    batch = make_batch(cfg, n_points=30000)
    t = time.perf_counter()
    with torch.no_grad():
        out = model(batch).head
    dt = time.perf_counter() - t
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"\npaper full forward (B=1, 6 x 640 x 1600): {dt:.1f} s, peak RSS {peak_gb:.1f} GB, "
          f"{count_parameters(model):,} parameters")
    A = len(cfg.class_names) * len(cfg.anchor_rotations)
    assert out.cls_logits.shape == (1, A, 180, 180)
    assert torch.isfinite(out.cls_logits).all() and torch.isfinite(out.box_deltas).all()
