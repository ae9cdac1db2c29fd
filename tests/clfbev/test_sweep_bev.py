"""The sweep bands: each point counted once, in its own cell and lag band, each band's mean offset
in its cell, each cell's fitted trail, and the lidar BEV carries them as its last channels."""
import math

import pytest
import torch

from clfbev.lidar_encoder import LidarEncoder
from clfbev.config import ModelConfig
from clfbev.errors import ConfigError
from clfbev.sweep_bev import TRAIL_MIN_POINTS, sweep_occupancy, sweep_trails

pytestmark = pytest.mark.usefixtures("one_thread")

RANGE = (-6.4, -6.4, -2.0, 6.4, 6.4, 2.0)    # 8 x 8 BEV cells of 1.6 m


def random_points(n: int, seed: int) -> torch.Tensor:
    """(n, 5) points uniform over RANGE, intensity in [0, 1), lags of the 10 sweeps."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(RANGE[:3]), torch.tensor(RANGE[3:])
    return torch.cat([lo + (hi - lo) * torch.rand(n, 3, generator=g), torch.rand(n, 1, generator=g),
                      torch.randint(0, 10, (n, 1), generator=g) * 0.05], dim=1)


def test_points_land_in_their_cell_and_band():
    # x, y, z, intensity, lag; 10 sweeps of 0.05 s over a 0.45 s span, 5 bands of 0.09 s.
    pts = torch.tensor([
        [0.1, 0.1, 0.0, 0.0, 0.00],    # cell (iy 4, ix 4), band 0
        [0.2, 0.3, 0.5, 0.0, 0.05],    # same cell, 0.05 s: still band 0
        [0.2, 0.3, 0.5, 0.0, 0.10],    # band 1
        [-6.3, 6.3, 0.0, 0.0, 0.45],   # corner cell (iy 7, ix 0), the oldest sweep: band 4
        [-6.3, 6.3, 0.0, 0.0, 0.60],   # older than the span: the last band too
        [6.5, 0.0, 0.0, 0.0, 0.00],    # outside x
        [0.0, 0.0, 2.5, 0.0, 0.00],    # outside z
        [0.1, 0.1, 0.0, 0.0, 0.20],    # the second sample: cell (4, 4), band 2
    ])
    batch = torch.tensor([0, 0, 0, 0, 0, 0, 0, 1])
    bev = sweep_occupancy(pts, batch, 2, RANGE, (8, 8), 5, 0.45)
    expected = torch.zeros(2, 5, 8, 8)
    expected[0, 0, 4, 4] = math.log(3.0)          # log(1 + 2 points)
    expected[0, 1, 4, 4] = math.log(2.0)
    expected[0, 4, 7, 0] = math.log(3.0)
    expected[1, 2, 4, 4] = math.log(2.0)
    torch.testing.assert_close(bev, expected)


def test_offsets_are_each_bands_mean_position_in_its_cell():
    # Cell (iy 4, ix 4) spans x and y 0 to 1.6 m, centre 0.8: offsets in cells of 1.6 m.
    pts = torch.tensor([
        [0.1, 0.1, 0.0, 0.0, 0.00],    # band 0
        [0.5, 0.3, 0.5, 0.0, 0.05],    # band 0: mean (0.3, 0.2)
        [1.5, 1.2, 0.5, 0.0, 0.40],    # band 4
        [6.5, 0.0, 0.0, 0.0, 0.00],    # outside x: nowhere
        [-6.3, 6.3, 0.0, 0.0, 0.20],   # the second sample: corner cell (7, 0), band 2
    ])
    batch = torch.tensor([0, 0, 0, 0, 1])
    both = sweep_occupancy(pts, batch, 2, RANGE, (8, 8), 5, 0.45, offsets=True)
    off = both[:, 5:]
    expected = torch.zeros(2, 10, 8, 8)
    expected[0, 0:2, 4, 4] = torch.tensor([(0.3 - 0.8) / 1.6, (0.2 - 0.8) / 1.6])
    expected[0, 8:10, 4, 4] = torch.tensor([(1.5 - 0.8) / 1.6, (1.2 - 0.8) / 1.6])
    expected[1, 4:6, 7, 0] = torch.tensor([(-6.3 + 6.4) / 1.6 - 0.5, (6.3 - 4.8) / 1.6 - 0.5])
    torch.testing.assert_close(off, expected)
    torch.testing.assert_close(both[:, :5], sweep_occupancy(pts, batch, 2, RANGE, (8, 8), 5, 0.45))


def test_a_walkers_trail_inside_one_cell_shows_in_the_offsets_not_the_counts():
    """1.2 m/s along x over 10 sweeps: the counts of every band sit in the same cell, the newest
    band's mean x lies ahead of the oldest's by the trail."""
    lag = torch.arange(10).repeat_interleave(20) * 0.05
    x = 0.3 + 1.2 * (0.45 - lag) + 0.05 * torch.randn(200, generator=torch.Generator().manual_seed(0))
    pts = torch.stack([x, torch.full_like(x, 0.8), torch.zeros_like(x), torch.zeros_like(x), lag], dim=1)
    batch = torch.zeros(200, dtype=torch.long)
    counts = sweep_occupancy(pts, batch, 1, RANGE, (8, 8), 5, 0.45)
    assert (counts[0, :, 4, 4] == math.log(41.0)).all() and counts.count_nonzero() == 5
    off = sweep_occupancy(pts, batch, 1, RANGE, (8, 8), 5, 0.45, offsets=True)[:, 5:]
    trail_m = (off[0, 0, 4, 4] - off[0, 8, 4, 4]) * 1.6
    assert abs(trail_m - 1.2 * 0.4) < 0.03     # band 0 (lags 0, 0.05) to band 4 (0.4, 0.45)


def test_lidar_bev_ends_with_the_bands():
    pts = random_points(2000, 0)
    torch.manual_seed(0)
    enc = LidarEncoder(5, 16, (8, 16, 16), RANGE, (0.4, 0.4, 0.4), 100000, time_lag_span=0.45,
                       sweep_bands=5).eval()
    plain = LidarEncoder(5, 16, (8, 16, 16), RANGE, (0.4, 0.4, 0.4), 100000, time_lag_span=0.45).eval()
    plain.load_state_dict(enc.state_dict())
    with torch.no_grad():
        bev, base = enc([pts]), plain([pts])
    assert enc.out_channels == plain.out_channels + 5 == bev.shape[1]
    torch.testing.assert_close(bev[:, :-5], base, rtol=0, atol=0)
    ny, nx = enc.out_size
    torch.testing.assert_close(bev[:, -5:], sweep_occupancy(pts, torch.zeros(2000, dtype=torch.long), 1, RANGE,
                                                            (ny, nx), 5, 0.45))
    assert bev[0, -5:].exp().sub(1).sum().round() == 2000   # every point counted once
    # The velocity tower gets the bands by name: encode() hands them over as the motion features.
    with torch.no_grad():
        feats, plain_feats = enc.encode([pts]), plain.encode([pts])
    assert torch.equal(feats.bev, bev) and torch.equal(feats.motion, bev[:, -5:]) and plain_feats.motion is None
    with torch.no_grad():
        empty = enc.encode([pts[:0]])                   # no point: an empty BEV, empty motion features
    assert empty.motion.shape == (1, 5, ny, nx) and not empty.bev.any()


def test_lidar_bev_with_offsets_ends_with_the_counts_then_the_offsets():
    pts = random_points(500, 1)
    enc = LidarEncoder(5, 16, (8, 16, 16), RANGE, (0.4, 0.4, 0.4), 100000, time_lag_span=0.45,
                       sweep_bands=5, sweep_offsets=True).eval()
    with torch.no_grad():
        feats = enc.encode([pts])
    ny, nx = enc.out_size
    grid = (pts, torch.zeros(500, dtype=torch.long), 1, RANGE, (ny, nx), 5, 0.45)
    assert enc.out_channels == enc.sparse.out_channels + 15 == feats.bev.shape[1]
    torch.testing.assert_close(feats.motion[:, :5], sweep_occupancy(*grid))
    torch.testing.assert_close(feats.motion, sweep_occupancy(*grid, offsets=True))
    assert torch.equal(feats.bev[:, -15:], feats.motion)


def moving_cluster(centre, velocity, z=0.0, per_sweep=4, sweeps=10):
    """(sweeps * per_sweep, 5) points of a rigid cluster at ``centre`` in the key frame, moving
    at ``velocity`` m/s: each sweep's points lie where the cluster was ``lag`` seconds ago."""
    spread = torch.tensor([[0.0, 0.0], [0.2, 0.0], [0.0, 0.2], [0.2, 0.2]])[:per_sweep]
    rows = []
    for k in range(sweeps):
        lag = 0.05 * k
        xy = torch.tensor(centre) - lag * torch.tensor(velocity) + spread
        rows.append(torch.cat([xy, torch.full((per_sweep, 1), z), torch.zeros(per_sweep, 1),
                               torch.full((per_sweep, 1), lag)], dim=1))
    return torch.cat(rows)


def test_a_trail_inside_one_cell_reads_its_velocity_exactly_on_both_windows():
    """A walker at (1.2, -0.5) m/s whose 10 sweeps stay in cell (iy 4, ix 4); under it the road's
    points (below min_z) slide with the ego at 8 m/s, a parked object sits in another cell, and
    a cell holds too few points to fit."""
    walker = moving_cluster((0.9, 0.9), (1.2, -0.5))
    road = moving_cluster((0.6, 0.4), (-8.0, 0.0), z=-1.8)
    parked = moving_cluster((-4.0, -4.0), (0.0, 0.0))
    sparse = moving_cluster((4.0, -4.0), (3.0, 0.0), per_sweep=1)[:TRAIL_MIN_POINTS - 1]
    pts = torch.cat([walker, road, parked, sparse])
    trails = sweep_trails(pts, torch.zeros(len(pts), dtype=torch.long), 1, RANGE, (8, 8), min_z=-1.4)
    assert trails.shape == (1, 4, 8, 8)
    for window in (0, 1):
        torch.testing.assert_close(trails[0, 2 * window:2 * window + 2, 4, 4], torch.tensor([1.2, -0.5]))
    assert trails[0, :2, 1, 1].abs().max() < 1e-6                    # parked: 0 m/s
    assert trails[0, :, 1, 6].abs().max() == 0                      # five points: no fit
    with_road = sweep_trails(pts, torch.zeros(len(pts), dtype=torch.long), 1, RANGE, (8, 8), min_z=-5.0)
    assert (with_road[0, :2, 4, 4] - torch.tensor([1.2, -0.5])).abs().max() > 0.5   # the road would spoil it


def test_a_trail_across_cells_is_read_by_the_neighbourhood_window():
    """A car at 10 m/s along y: its 0.45 s trail crosses three 1.6 m cells; the 3x3 window
    around its key-frame cell holds the whole trail and reads 10 m/s; the cell alone holds a
    part of it; a second sample in the batch is independent."""
    car = moving_cluster((0.8, 3.0), (0.0, 10.0))
    pts = torch.cat([car, moving_cluster((0.8, 0.8), (-1.0, 0.0))])
    batch = torch.tensor([0] * len(car) + [1] * 40)
    trails = sweep_trails(pts, batch, 2, RANGE, (8, 8), min_z=-1.4)
    iy = int((3.0 + 6.4) // 1.6)
    torch.testing.assert_close(trails[0, 2:, iy, 4], torch.tensor([0.0, 10.0]))
    assert trails[0, 1, iy, 4] < 9.0
    torch.testing.assert_close(trails[1, :, 4, 4], torch.tensor([-1.0, 0.0, -1.0, 0.0]))


def test_lidar_bev_with_trails_ends_with_them():
    pts = random_points(500, 2)
    enc = LidarEncoder(5, 16, (8, 16, 16), RANGE, (0.4, 0.4, 0.4), 100000, time_lag_span=0.45,
                       sweep_bands=5, sweep_offsets=True, trail_min_z=-1.0).eval()
    with torch.no_grad():
        feats = enc.encode([pts])
    ny, nx = enc.out_size
    batch = torch.zeros(500, dtype=torch.long)
    assert enc.out_channels == enc.sparse.out_channels + 19 == feats.bev.shape[1]
    bands = sweep_occupancy(pts, batch, 1, RANGE, (ny, nx), 5, 0.45, offsets=True)
    torch.testing.assert_close(feats.motion[:, :15], bands)
    torch.testing.assert_close(feats.motion[:, 15:], sweep_trails(pts, batch, 1, RANGE, (ny, nx), -1.0))
    assert feats.motion[:, 15:].abs().sum() > 0


def test_config_counts_the_trail_channels_and_needs_the_bands():
    assert ModelConfig(n_sweeps=10, sweep_bands=5, sweep_offsets=True, sweep_trail=True).sweep_channels == 19
    with pytest.raises(ConfigError, match="sweep_trail need"):
        ModelConfig(n_sweeps=10, sweep_trail=True)


def test_trails_kept_out_of_the_bev_still_reach_the_motion_features():
    pts = random_points(500, 2)
    kw = dict(time_lag_span=0.45, sweep_bands=5, sweep_offsets=True, trail_min_z=-1.0)
    torch.manual_seed(0)
    inside = LidarEncoder(5, 16, (8, 16, 16), RANGE, (0.4, 0.4, 0.4), 100000, **kw).eval()
    torch.manual_seed(0)
    outside = LidarEncoder(5, 16, (8, 16, 16), RANGE, (0.4, 0.4, 0.4), 100000, trail_in_bev=False, **kw).eval()
    with torch.no_grad():
        a, b = inside.encode([pts]), outside.encode([pts])
    assert outside.out_channels == outside.sparse.out_channels + 15 == b.bev.shape[1]
    torch.testing.assert_close(b.bev, a.bev[:, :-4])
    torch.testing.assert_close(b.motion, a.motion)
    assert b.motion[:, 15:].abs().sum() > 0


def test_config_keeps_the_trails_out_of_the_bev_only_for_a_velocity_tower():
    cfg = ModelConfig(n_sweeps=10, sweep_bands=5, sweep_offsets=True, sweep_trail=True, velocity_tower=16,
                      sweep_trail_in_bev=False)
    assert cfg.sweep_channels == 19
    assert cfg.lidar_bev_channels == ModelConfig(n_sweeps=10, sweep_bands=5, sweep_offsets=True).lidar_bev_channels
    with pytest.raises(ConfigError, match="sweep_trail_in_bev false needs a velocity_tower"):
        ModelConfig(n_sweeps=10, sweep_bands=5, sweep_trail=True, sweep_trail_in_bev=False)
