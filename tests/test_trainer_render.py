"""Rays, packed compositing and the grid field on small hand-checked cases."""
import copy
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from spikenerf.model import GridField  # noqa: E402
from spikenerf.render import (_exclusive_segment_cumsum, _occupied_samples, box_interval, pixel_rays,  # noqa: E402
                              render_image, render_rays, visible_samples)


def _look_from_z(dist=4.0):
    pose = torch.eye(4)
    pose[2, 3] = dist  # camera on +z looking down -z at the origin
    return pose


def test_centre_pixel_looks_down_minus_z():
    pose = _look_from_z()
    o, d = pixel_rays(pose[None].expand(1, 4, 4), torch.tensor([5 * 10 + 5]), 10, 10, 20.0)
    assert torch.allclose(o, torch.tensor([[0.0, 0.0, 4.0]]))
    assert torch.allclose(d, torch.tensor([[0.025, -0.025, -1.0]]) / math.sqrt(1 + 2 * 0.025 ** 2))


def test_ray_origins_are_their_own_contiguous_copy():
    """The renderer gathers each sample's ray origin; from a strided view of the poses (one pose
    expanded over a view, or a batch of poses) PyTorch's CPU gather is many times slower
    (bench/bench_trainer_step.py --origins), so the origins come back contiguous, values unchanged."""
    pose = _look_from_z()
    for poses in (pose[None].expand(6, 4, 4), torch.stack([pose, pose + 0.5, pose - 1.0])):
        n = poses.shape[0]
        o, d = pixel_rays(poses, torch.arange(n), 10, 10, 20.0)
        assert o.is_contiguous() and d.is_contiguous()
        assert torch.equal(o, poses[:, :3, 3])
        o[0, 0] = 7.0  # a copy: the poses are not written through it
        assert poses[0, 0, 3] != 7.0


def test_box_interval_hit_and_miss():
    o = torch.tensor([[0.0, 0.0, 4.0], [5.0, 5.0, 4.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    t_in, t_out = box_interval(o, d, box)
    assert t_in[0] == pytest.approx(3.0) and t_out[0] == pytest.approx(5.0)
    assert t_out[1] <= t_in[1]


def test_segment_cumsum():
    v = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0])
    seg = torch.tensor([0, 0, 2, 2, 2])
    assert torch.equal(_exclusive_segment_cumsum(v, seg, 3), torch.tensor([0.0, 1.0, 0.0, 3.0, 7.0]))


def _cube_field(value=0.25):
    f = GridField(grid_size=33, final_size=33, bound=1.5)
    with torch.no_grad():
        f.grid[0, 0] = -30.0  # empty
        f.grid[0, 0, 11:22, 11:22, 11:22] = 30.0  # an opaque cube |x| <= 0.5
        f.grid[0, 1] = math.log(value / (1 - value))
    return f


def test_opaque_cube_renders_its_colour_on_white():
    f = _cube_field(0.25)
    o = torch.tensor([[0.0, 0.0, 4.0], [1.0, 1.0, 4.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    with torch.no_grad():
        x, acc = render_rays(f, o, d)
    x, acc = x.tolist(), acc.tolist()
    assert acc[0] == pytest.approx(1.0, abs=1e-4) and x[0] == pytest.approx(0.25, abs=1e-3)
    assert acc[1] == pytest.approx(0.0, abs=1e-4) and x[1] == pytest.approx(1.0, abs=1e-4)


def test_occupancy_skipping_does_not_change_the_image():
    f = _cube_field(0.6)
    pose = _look_from_z()
    full, _ = render_image(f, pose, 12, 12, 15.0)
    frac = f.update_occupancy(1e-3)
    assert frac < 0.2
    assert torch.all(f.box[1] < 1.0)
    skipped, _ = render_image(f, pose, 12, 12, 15.0)
    assert torch.allclose(full, skipped, atol=1e-5)


def test_upsample_keeps_the_field():
    f = _cube_field(0.6)
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.2, -1.0, 0.3]])
    before = f.sample_grid(pts)
    f.upsample(65)
    assert f.grid_size == 65 and f.occupancy.shape == (65, 65, 65)
    assert torch.allclose(f.sample_grid(pts), before, atol=1e-4)


def test_gradients_reach_the_grid():
    f = GridField(grid_size=16, final_size=16)
    o = torch.tensor([[0.0, 0.0, 4.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]])
    x, _ = render_rays(f, o, d, jitter=torch.tensor([0.3]))
    x.sum().backward()
    assert f.grid.grad is not None and torch.count_nonzero(f.grid.grad) > 0


def test_sh_field_shades_by_viewing_direction():
    """Degree-1 SH: a coefficient on the z harmonic brightens the cube seen from +z, darkens it from -z."""
    f = _cube_field(0.5)
    f_sh = GridField(grid_size=33, final_size=33, bound=1.5, sh_degree=1)
    assert f_sh.sh.shape == (1, 3, 16, 16, 16)  # coarser: sh_scale 2
    with torch.no_grad():
        f_sh.grid.copy_(f.grid)
        f_sh.sh[0, 1] = 2.0  # the z harmonic (0.4886 z)
    o = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, -4.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    with torch.no_grad():
        x, acc = render_rays(f_sh, o, d)
    # the ray travelling along -z sees the z term with dir z = -1, and the other way round
    expect = [1 / (1 + math.exp(2.0 * 0.48860251)), 1 / (1 + math.exp(-2.0 * 0.48860251))]
    assert acc.tolist() == pytest.approx([1.0, 1.0], abs=1e-4)
    assert x.tolist() == pytest.approx(expect, abs=1e-3)


def test_sh_grid_grows_trains_and_round_trips():
    f = GridField(grid_size=16, final_size=32, sh_degree=2)
    assert f.sh.shape[1] == 8 and len(f.grids()) == 2
    x, _ = render_rays(f, torch.tensor([[0.0, 0.0, 4.0]]), torch.tensor([[0.0, 0.0, -1.0]]),
                       jitter=torch.tensor([0.3]))
    x.sum().backward()
    assert f.sh.grad is not None and torch.count_nonzero(f.sh.grad) > 0
    f.upsample(32)
    assert f.sh.shape[-1] == 16
    g = GridField(**f.config())
    g.load_state_dict(f.state_dict())  # a checkpoint's field is rebuilt from its stored configuration
    assert torch.equal(g.sh, f.sh)
    with pytest.raises(ValueError):
        GridField(features=4, sh_degree=1)


def test_window_poses_follow_the_subframe_poses():
    from spikenerf.data import interpolate_pose
    from spikenerf.targets import window_bounds

    def rot_z(a):
        m = np.eye(4)
        m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        m[:3, 3] = [4 * np.cos(a), 4 * np.sin(a), 1.0]
        return m

    sub = np.stack([rot_z(0.01 * k) for k in range(16)])  # K = 16 poses over T = 256 frames
    assert np.allclose(interpolate_pose(sub, 8.0, 256), sub[0])  # sub-frame k sits at frame (k + 0.5) * 16
    assert np.allclose(interpolate_pose(sub, 0.0, 256), sub[0])  # held before the first centre
    mid = interpolate_pose(sub, 16.0, 256)  # half way between sub-frames 0 and 1
    assert np.allclose(mid[:3, :3] @ mid[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.allclose(mid[:3, :3], rot_z(0.005)[:3, :3], atol=1e-5)
    assert window_bounds(256, 8) == [(32 * w, 32 * w + 32) for w in range(8)]


def test_split_trilinear_matches_one_batch_in_values_and_gradients():
    """The CPU path samples many points as two batches of an expanded grid: same values, same gradient."""
    import torch.nn.functional as F

    from spikenerf.model import _trilinear
    gen = torch.Generator().manual_seed(3)
    grid = torch.randn(1, 3, 12, 12, 12, generator=gen, requires_grad=True)
    coords = torch.rand(4097, 3, generator=gen) * 2 - 1  # odd count: the second batch is padded
    assert coords.shape[0] * 64 >= grid.numel()  # enough points for the split path
    up = torch.randn(4097, 3, generator=gen)
    ref = F.grid_sample(grid, coords.view(1, -1, 1, 1, 3), mode="bilinear", align_corners=True).view(3, -1).t()
    (ref * up).sum().backward()
    ref_grad, grid.grad = grid.grad.clone(), None
    got = _trilinear(grid, coords)
    (got * up).sum().backward()
    assert got.shape == (4097, 3)
    assert torch.allclose(got, ref, atol=1e-6)
    assert torch.allclose(grid.grad, ref_grad, atol=1e-5)


@pytest.mark.parametrize("spread", [True, False])
def test_packed_samples_equal_a_ray_by_ray_march(spread):
    """Both ways of making candidates (broadcast for a field that fills its box, gather otherwise)
    give exactly the samples of a plain per-ray march through the occupied cells."""
    from spikenerf.render import _occupied_samples
    f = _cube_field(0.5)
    if not spread:
        f.update_occupancy(1e-3)  # a tight box: most candidates lie outside it
    gen = torch.Generator().manual_seed(1)
    pose = _look_from_z()
    o, d = pixel_rays(pose[None].expand(64, 4, 4), torch.randint(0, 400, (64,), generator=gen), 20, 20, 25.0)
    jitter = torch.rand(64, generator=gen)
    step = f.step_ratio * f.voxel
    idx, ray_of, pts = _occupied_samples(f, o, d, step, jitter)
    t_in, t_out = box_interval(o, d, f.box)
    expect_rays, expect_pts = [], []
    for r in range(64):
        t = float(t_in[r]) + step * (float(jitter[r]))
        while t < float(t_out[r]):
            p = o[r] + t * d[r]
            if bool(f.occupied(p[None])[0]):
                expect_rays.append(r)
                expect_pts.append(p)
            t += step
    assert len(expect_rays) > 0
    assert ray_of.tolist() == expect_rays
    assert torch.allclose(pts, torch.stack(expect_pts), atol=1e-5)


@pytest.mark.parametrize("case", ["scattered", "compact", "two objects", "cropped", "inside", "long rays"])
def test_skipping_empty_blocks_gives_the_same_samples_to_the_bit(case, monkeypatch):
    """The two-pass walk (stretches of samples tested against the block mask first) returns
    exactly the one-pass samples: same indices, same rays, same points bit for bit, same order;
    for rays from outside and inside the box, with and without jitter, on a cropped grid, and
    for rays whose direction is not a unit vector."""
    import spikenerf.render as R
    from spikenerf.render import SKIP_MAX_KEPT, _occupied_samples, _segment_length
    gen = torch.Generator().manual_seed(3)
    f = GridField(grid_size=65, final_size=65, bound=1.5)
    with torch.no_grad():
        f.grid[0, 0] = torch.randn(65, 65, 65, generator=gen) - (2.0 if case == "scattered" else 30.0)
        x = torch.linspace(-1.5, 1.5, 65)
        # a ball with holes plus one floater, or two such balls in opposite corners (empty space
        # between them inside the box, where stretches are skipped next to occupied blocks)
        for c, radius in (((-0.9, 0.35), (0.9, 0.35)) if case == "two objects" else ((0.0, 0.6),)):
            if case == "scattered":
                break
            r = ((x[:, None, None] - c) ** 2 + (x[None, :, None] - c) ** 2 + (x[None, None, :] - c) ** 2).sqrt()
            f.grid[0, 0][(r < radius) & (torch.rand(65, 65, 65, generator=gen) < 0.5)] = 5.0
        if case in ("compact", "cropped", "inside", "long rays"):
            f.grid[0, 0, 5, 60, 30] = 5.0
    f.update_occupancy(1e-2)
    if case == "cropped":
        f.crop(torch.tensor([-0.9, -0.8, -0.7]), torch.tensor([0.8, 1.4, 0.9]))
        f.update_occupancy(1e-2)
    n = 300
    origins = torch.randn(n, 3, generator=gen)
    if case == "inside":
        origins = origins * 0.3
    else:
        origins = 4.0 * origins / origins.norm(dim=-1, keepdim=True)
    target = (0.9 if case == "two objects" else 0.5) * torch.randn(n, 3, generator=gen)
    dirs = target - origins
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    if case == "long rays":
        dirs = dirs * 1.7  # samples 1.7 steps apart in space
    step = f.step_ratio * f.voxel
    assert _segment_length(f, dirs, step) > 1
    for jitter in (None, torch.rand(n, generator=gen)):
        one = _occupied_samples(f, origins, dirs, step, jitter, coarse=False)
        assert one[0].numel() > 300
        assert torch.equal(_occupied_samples(f, origins, dirs, step, jitter, coarse=False, broadcast=True)[2], one[2])
        for never_hand_back in (True, False):
            monkeypatch.setattr(R, "SKIP_MAX_KEPT", 1.0 if never_hand_back else SKIP_MAX_KEPT)
            f._skip_probe = None
            two = _occupied_samples(f, origins, dirs, step, jitter)
            if never_hand_back:  # the samples came from the block pass
                assert f._skip_probe[2] is False
            for a, b in zip(one, two):
                assert torch.equal(a, b)


def test_block_mask_follows_the_occupancy_and_is_conservative():
    """coarse_occupied is True wherever an occupied grid point lies within COARSE points of a
    point's nearest grid point, and follows occupancy changes made in place or by replacement."""
    from spikenerf.model import COARSE
    f = GridField(grid_size=41, final_size=41, bound=1.5)
    f.occupancy = torch.zeros(41, 41, 41, dtype=torch.bool)
    pts = (torch.rand(4000, 3, generator=torch.Generator().manual_seed(4)) * 3.6 - 1.8)
    assert not f.coarse_occupied(pts).any()
    f.occupancy[17, 3, 40] = True  # in place
    cell = f._cell(pts)
    near = ((cell - torch.tensor([17.0, 3.0, 40.0])).abs() <= COARSE).all(-1)
    assert near.any() and bool(f.coarse_occupied(pts)[near].all())
    assert not f.coarse_occupied(pts)[((cell - torch.tensor([17.0, 3.0, 40.0])).abs() > 3 * COARSE).any(-1)].any()
    f.occupancy = torch.zeros(41, 41, 41, dtype=torch.bool)  # replaced
    assert not f.coarse_occupied(pts).any()


def test_fitted_box_ignores_a_floater_and_the_crop_keeps_the_field():
    """The box of the solid grid points less their extreme 0.1 % per axis: one isolated solid
    voxel far away (a floater, 1 of 1332) does not stretch it, faint haze does not count; cropping
    cuts the grid values out exactly and rendering is unchanged."""
    f = _cube_field(0.6)
    with torch.no_grad():
        f.grid[0, 1] = torch.linspace(-2, 2, 33)[:, None, None]  # luminance varies along x
        f.grid[0, 0, 1, 1, 30] = 30.0  # a floater near a corner
        f.grid[0, 0, 28:, :, :4] = f._raw_for_alpha(0.1)  # haze: sample alpha 0.1
    pose = _look_from_z()
    clean = copy.deepcopy(f)  # the same field without the floater and the haze
    with torch.no_grad():
        clean.grid[0, 0, 1, 1, 30] = -30.0
        clean.grid[0, 0, 28:, :, :4] = -30.0
    clean.update_occupancy(1e-3)
    before, _ = render_image(clean, pose, 12, 12, 15.0)
    lo, hi = f.fitted_box(alpha=0.3, trim=1e-3, pad=2)
    v = f.voxel  # 3 / 32; the cube's points are indices 11..21
    assert torch.allclose(lo, torch.full((3,), -1.5 + 9 * v)) and torch.allclose(hi, torch.full((3,), -1.5 + 23 * v))
    pts = torch.tensor([[0.1, -0.2, 0.3], [-0.4, 0.45, 0.0]])
    vals = f.sample_grid(pts)
    f.crop(lo, hi)
    f.update_occupancy(1e-3)
    assert f.dims == (15, 15, 15) and f.occupancy.shape == (15, 15, 15)
    assert f.voxel == pytest.approx(v) and f.grid_size == 33
    assert torch.allclose(f.sample_grid(pts), vals, atol=1e-5)
    assert torch.allclose(f.box, clean.box)  # the floater and the haze were cut off with the box
    after, _ = render_image(f, pose, 12, 12, 15.0)
    assert torch.allclose(before, after, atol=1e-5)


def test_a_cropped_box_grows_with_cubic_voxels_and_round_trips():
    f = _cube_field(0.6)
    f.update_occupancy(1e-3)
    f.crop(torch.tensor([-0.6, -0.6, -0.9]), torch.tensor([0.6, 0.6, 0.9]))
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 0.5]])
    before = f.sample_grid(pts)
    f.upsample(65)  # the voxel edge of 65 points across [-1.5, 1.5]: 3 / 64
    assert f.grid_size == 65
    edges = (f.aabb[1] - f.aabb[0]) / (torch.tensor(f.dims) - 1)
    assert torch.allclose(edges, torch.full((3,), 3 / 64), atol=1e-6)
    assert f.dims[2] > f.dims[0]  # the box is taller in z
    assert torch.allclose(f.sample_grid(pts), before, atol=1e-4)
    g = GridField(**f.config())
    g.load_state_dict(f.state_dict())
    assert torch.equal(g.grid, f.grid) and torch.equal(g.aabb, f.aabb) and g.dims == f.dims
    o, d = torch.tensor([[0.2, 0.1, 4.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    with torch.no_grad():
        assert torch.equal(render_rays(f, o, d)[0], render_rays(g, o, d)[0])


def test_the_kept_voxel_edge_follows_every_change_of_the_box():
    """GridField.voxel is kept between calls (a read of the box waits for a GPU): it must follow a crop,
    a growth, a box loaded in place and a box replaced."""
    def edge(f):
        return float((f.aabb[1, 0] - f.aabb[0, 0]) / (f.dims[0] - 1))

    f = _cube_field(0.6)
    f.update_occupancy(1e-3)
    assert f.voxel == edge(f)
    f.crop(torch.tensor([-0.6, -0.6, -0.9]), torch.tensor([0.6, 0.6, 0.9]))
    assert f.voxel == edge(f)
    f.upsample(65)
    assert f.voxel == edge(f) == pytest.approx(3 / 64)
    g = GridField(**f.config())
    assert g.voxel == f.voxel
    state = f.state_dict()
    state["aabb"] = state["aabb"] * 2
    box = g.aabb
    g.load_state_dict(state)  # a box twice the size, copied in place (the same tensor, a new version)
    assert g.aabb is box and g.voxel == pytest.approx(2 * f.voxel)
    with torch.no_grad():
        g.aabb.mul_(0.5)  # halved in place
    assert g.voxel == f.voxel
    g.aabb = f.aabb * 3  # replaced
    assert g.voxel == pytest.approx(3 * f.voxel)


def test_tv_at_points_is_the_neighbour_differences_where_the_step_read():
    f = GridField(grid_size=5, final_size=5, bound=1.0)
    with torch.no_grad():
        f.grid[0, 0] = torch.arange(125.0).view(5, 5, 5)  # x stride 25, y 5, z 1
        f.grid[0, 1] = torch.arange(125.0).view(5, 5, 5) ** 2 / 10
    f.query(torch.tensor([[-0.3, 0.2, 0.6]]), torch.tensor([[0.0, 0.0, 1.0]]))  # grid position (1.4, 2.4, 3.2)
    tv = f.tv_at_points(torch.Generator().manual_seed(0), n=16)
    base = 1 * 25 + 2 * 5 + 3  # the lowest corner (1, 2, 3)
    want = 0.0
    for step in (25, 5, 1):
        d0 = step  # channel 0 differs by the stride
        d1 = ((base + step) ** 2 - base ** 2) / 10
        want += (d0 ** 2 + d1 ** 2) / 2  # the mean over the two channels
    assert float(tv.detach()) == pytest.approx(want, rel=1e-6)
    tv.backward()
    assert f.grid.grad[0, 0, 1, 2, 3] < 0 and f.grid.grad[0, 0, 2, 2, 3] > 0
    assert torch.count_nonzero(f.grid.grad[0, 0]) == 4  # the corner and its three neighbours


def test_the_block_prior_keeps_its_strength_per_voxel_on_a_cropped_grid():
    """A block covers a larger share of a cropped grid; the prior is scaled by the grid's share of
    the cube's points, so each voxel's expected prior is the cube's."""
    f = GridField(grid_size=40, final_size=40)
    with torch.no_grad():
        f.grid.normal_(generator=torch.Generator().manual_seed(0))
    full = f.tv_loss(torch.Generator().manual_seed(1), block=10)
    assert f.grid_size == 40
    f.crop(torch.tensor([-0.5, -0.5, -0.5]), torch.tensor([0.5, 0.5, 0.5]))
    share = f.grid[0, 0].numel() / 40 ** 3
    assert 0.03 < share < 0.06
    crop = f.tv_loss(torch.Generator().manual_seed(1), block=10)
    # i.i.d. values: the block's mean squared difference is the same anywhere, so the scaled prior is share x
    assert float(crop.detach()) == pytest.approx(share * float(full.detach()), rel=0.15)


def test_the_prior_on_the_luminance_in_its_logit_in_itself_or_not_at_all():
    """``tv_loss(luminance=...)``: a dark surface (logit -6.5, luminance 0.0015) beside voxels never seen
    (logit 0, luminance 0.5). On the logit the prior pulls the dark voxels up as hard as any; on the luminance
    (times 4, the logit's slope at grey) its pull there is about 0.004 times that, on its sRGB encoding (scaled
    likewise) about 0.08 times; off, none. The density's part is the same in every mode, and the default is the
    logit."""
    f = GridField(grid_size=8, final_size=8, sh_degree=1)
    with torch.no_grad():
        f.grid[0, 0].normal_(generator=torch.Generator().manual_seed(0))
        f.grid[0, 1, :4] = -6.5
    grads = {}
    for mode in ("logit", "linear", "srgb", "off"):
        f.grid.grad = None
        f.tv_loss(torch.Generator().manual_seed(1), block=8, luminance=mode).backward()
        grads[mode] = f.grid.grad[0].clone()
    assert torch.equal(grads["logit"][0], grads["off"][0])
    assert torch.allclose(grads["logit"][0], grads["linear"][0]) and torch.allclose(grads["logit"][0], grads["srgb"][0])
    edge = grads["logit"][1, 3]  # the dark voxels next to the grey ones: pulled up (a negative gradient)
    assert (edge < 0).all() and torch.count_nonzero(grads["off"][1]) == 0
    s = torch.sigmoid(torch.tensor(-6.5))
    # d/dz (4 s(z) - 4 s(0))^2 = 32 (s(z) - 0.5) s'(z) against d/dz (z - 0)^2 = 2 z
    assert torch.allclose(grads["linear"][1, 3] / edge, 16 * (s - 0.5) * s * (1 - s) / -6.5, rtol=1e-4)
    # the sRGB encoding's slope at 0.0015 is 12.92 (its linear part); k = 6.07 puts its slope in z at grey to 1
    k = 1.0 / (0.25 * 1.055 / 2.4 * 0.5 ** (1 / 2.4 - 1))
    srgb = lambda v: 1.055 * v ** (1 / 2.4) - 0.055  # noqa: E731 (above 0.0031308)
    want = k * k * (12.92 * s - srgb(torch.tensor(0.5))) * 12.92 * s * (1 - s) / -6.5
    assert torch.allclose(grads["srgb"][1, 3] / edge, want, rtol=1e-4) and 0.05 < float(want) < 0.1
    g = torch.Generator().manual_seed(1)
    default = f.tv_loss(g, block=8).detach()
    assert torch.equal(default, f.tv_loss(torch.Generator().manual_seed(1), block=8, luminance="logit").detach())
    with pytest.raises(ValueError, match="luminance"):
        f.tv_loss(luminance="gamma")


def test_early_termination_drops_only_what_the_ray_no_longer_sees():
    """Samples behind transmittance ``stop`` are dropped (early ray termination): on a cloud whose
    density rises inward, many are; the dropped ones are exactly those their ray reaches with
    transmittance below ``stop`` (a ray-by-ray product of (1 - alpha)); luminance and opacity move by
    less than ``stop``, and the grid's gradient by under 1 % of its largest value (a voxel sums the
    small terms of many dropped samples)."""
    f = GridField(grid_size=33, final_size=33, bound=1.5)
    ax = torch.linspace(-1.5, 1.5, 33)
    r = torch.sqrt(ax[:, None, None] ** 2 + ax[None, :, None] ** 2 + ax[None, None, :] ** 2)
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        f.grid[0, 0] = 12.0 * (1.0 - r) + 0.3 * torch.randn(33, 33, 33, generator=gen)
        f.grid[0, 1] = torch.randn(33, 33, 33, generator=gen)
    f.update_occupancy()
    n = 256
    o = torch.randn(n, 3, generator=gen) * 0.3 + torch.tensor([0.0, 0.0, 4.0])
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen) * 0.1 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    jitter = torch.rand(n, generator=gen)
    stop = 1e-3
    step = f.step_ratio * f.voxel
    _, ray_of, pts = _occupied_samples(f, o, d, step, jitter)
    keep, reads = visible_samples(f, ray_of, pts, n, step, stop)
    assert reads is not None and reads[0].shape == (8, len(ray_of))  # the main grid's corners, for the query
    assert keep is not None and 0.2 * len(ray_of) < len(ray_of) - len(keep) < 0.9 * len(ray_of)
    with torch.no_grad():  # the transmittance each sample is reached with, ray by ray
        alpha = 1 - torch.exp(-f.query(pts, d[ray_of])[0] * (step / f.ref_voxel))
    seen = torch.zeros(len(ray_of), dtype=torch.bool)
    for ray in range(n):
        at = (ray_of == ray).nonzero().squeeze(-1)
        reach = torch.cat([torch.ones(1), torch.cumprod(1 - alpha[at].double(), 0)[:-1]])
        seen[at] = reach >= stop
    assert torch.equal(seen.nonzero().squeeze(-1), keep)
    outs = []
    for s in (0.0, stop):
        f.grid.grad = None
        x, acc = render_rays(f, o, d, jitter, stop=s)
        (x * torch.linspace(-1, 1, n)).sum().backward()
        outs.append((x.detach(), acc.detach(), f.grid.grad.clone()))
    (x0, a0, g0), (x1, a1, g1) = outs
    assert float((x0 - x1).abs().max()) < stop and float((a0 - a1).abs().max()) < stop
    assert float((x0 - x1).abs().max()) > 0  # something was dropped from the composite
    assert float((g0 - g1).abs().max()) < 0.01 * float(g0.abs().max())
