"""The trainer's sparse path: corner-gather sampling, the lazy grid Adam, the fast occupancy, compact checkpoints."""
import pytest
import torch
import torch.nn.functional as F

from spikegen.errors import InputError
from spikenerf.model import GridField, corners
from spikenerf.optim import LazyGridAdam
from spikenerf.config import TrainConfig
from spikenerf import train as train_module
from spikenerf.train import _grow, field_from_checkpoint, make_optimizer, save_checkpoint
from test_trainer_cli import _cfg, dataset  # noqa: F401 (the tiny sphere dataset fixture)


def _field(seed=0, size=12, sh_degree=1, features=0):
    return randomised(GridField(grid_size=size, final_size=2 * size, sh_degree=sh_degree, features=features), seed)


def randomised(f, seed):
    """The field with its grids drawn from a standard normal (seeded)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in f.grids():
            p.normal_(generator=gen)
    return f


def _points(n, seed=1, spread=0.5):
    """Points in a part of the box (so that many voxels are never read) and unit directions."""
    gen = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=gen) * 2 - 1) * spread
    return pts, F.normalize(torch.randn(n, 3, generator=gen), dim=-1)


def _scatter(tape, grid):
    """Dense gradient of ``grid`` from its tape reads (the leaves' gradients summed per voxel)."""
    out = torch.zeros(grid.shape[1], grid[0, 0].numel())
    for g, idx, vals in tape:
        if g is grid:
            out.index_add_(1, idx, vals.grad)
    return out.view_as(grid)


def test_sparse_reads_match_grid_sample_in_values_and_gradients():
    f = _field()
    pts, dirs = _points(500)
    up = torch.randn(500, 2, generator=torch.Generator().manual_seed(2))
    sigma, x = f.query(pts, dirs)  # dense path: corner reads, the gradient added into grid.grad
    ((sigma * up[:, 0]).sum() + (x * up[:, 1]).sum()).backward()
    dense = [p.grad.clone() for p in f.grids()]
    f.sparse = True
    s2, x2 = f.query(pts, dirs)
    ((s2 * up[:, 0]).sum() + (x2 * up[:, 1]).sum()).backward()
    assert torch.allclose(s2, sigma, atol=1e-5) and torch.allclose(x2, x, atol=1e-6)
    assert len(f.tape) == 2  # one read per grid, nothing dense
    for p, ref in zip(f.grids(), dense):
        assert torch.allclose(_scatter(f.tape, p), ref, atol=1e-5)


def test_corners_weights_sum_to_one_and_hit_grid_points():
    unit = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [0.0, 0.5, -0.5]])
    idx, w = corners(unit, 5)  # grid points at -1, -0.5, 0, 0.5, 1
    assert torch.allclose(w.sum(1), torch.ones(3))
    assert idx[0, w[0].argmax()] == 0 and idx[1, w[1].argmax()] == 124  # the first and the last point
    assert idx[2, w[2].argmax()] == 2 * 25 + 3 * 5 + 1 and w[2].max() == 1  # exactly on (x, y, z) = (0, .5, -.5)


def test_sparse_tv_prior_equals_the_dense_one():
    f = _field(size=30)
    tv = f.tv_loss(torch.Generator().manual_seed(5), block=8)
    tv.backward()
    dense = [p.grad.clone() for p in f.grids()]
    f.sparse = True
    tv2 = f.tv_loss(torch.Generator().manual_seed(5), block=8)
    tv2.backward()
    assert torch.allclose(tv2, tv)
    for p, ref in zip(f.grids(), dense):
        assert torch.allclose(_scatter(f.tape, p), ref, atol=1e-7)


def _set_state(opt_dense, lazy, f, step, seed=3):
    """The same (random) moments and step count in a torch Adam and in the lazy one."""
    gen = torch.Generator().manual_seed(seed)
    lazy.step_count = step
    for i, p in enumerate(f.grids()):
        m = torch.randn(p.shape, generator=gen) * 0.1
        v = torch.rand(p.shape, generator=gen) * 0.01
        opt_dense.state[p] = {"step": torch.tensor(float(step)), "exp_avg": m.clone(), "exp_avg_sq": v.clone()}
        lazy.exp_avg[i].copy_(m.view_as(lazy.exp_avg[i]))
        lazy.exp_avg_sq[i].copy_(v.view_as(lazy.exp_avg_sq[i]))


def test_lazy_adam_step_is_dense_adams_on_the_read_voxels_and_leaves_the_rest():
    f = _field()
    ref = _field()  # the same values, trained by torch's dense Adam
    lazy = LazyGridAdam(f, lr_grid=0.1, lr_mlp=1e-3, betas=(0.9, 0.99))
    dense = torch.optim.Adam(ref.grids(), lr=0.1, betas=(0.9, 0.99))
    _set_state(dense, lazy, ref, step=7)
    before = [p.detach().clone() for p in f.grids()]
    m_before = [m.clone() for m in lazy.exp_avg]
    f.sparse = True
    pts, dirs = _points(300)
    sigma, x = f.query(pts, dirs)
    loss = sigma.square().mean() + x.mean() + 0.1 * f.tv_loss(torch.Generator().manual_seed(4), block=6)
    loss.backward()
    for p, q in zip(ref.grids(), f.grids()):
        p.grad = _scatter(f.tape, q)
    read = [torch.zeros(p[0, 0].numel(), dtype=torch.bool) for p in f.grids()]
    for g, idx, _ in f.tape:
        read[[q is g for q in f.grids()].index(True)][idx] = True
    lazy.step()
    dense.step()
    assert not f.tape  # the step consumed the reads
    for i, (p, q) in enumerate(zip(f.grids(), ref.grids())):
        C = p.shape[1]
        got, want, old = p.detach().view(C, -1), q.detach().view(C, -1), before[i].view(C, -1)
        assert 0 < int(read[i].sum()) < read[i].numel()  # some voxels read, some not
        assert torch.allclose(got[:, read[i]], want[:, read[i]], rtol=1e-6, atol=1e-7)
        assert torch.equal(got[:, ~read[i]], old[:, ~read[i]])  # untouched: parameters and moments unchanged
        assert torch.equal(lazy.exp_avg[i][:, ~read[i]], m_before[i][:, ~read[i]])
        assert not torch.allclose(want[:, ~read[i]], old[:, ~read[i]])  # (dense Adam does move them)
        assert torch.allclose(lazy.exp_avg[i][:, read[i]], dense.state[q]["exp_avg"].view_as(got)[:, read[i]])


def test_optimizer_state_round_trips_exactly_and_stays_compact():
    f = _field(size=24)
    f.sparse = True
    lazy = LazyGridAdam(f, lr_grid=0.1, lr_mlp=1e-3)
    for k in range(3):
        pts, dirs = _points(200, seed=10 + k, spread=0.3)
        sigma, x = f.query(pts, dirs)
        (sigma.mean() + x.mean()).backward()
        lazy.step()
    state = lazy.state_dict()
    assert state["grids"][0]["exp_avg"].shape[1] < 0.5 * f.grid[0, 0].numel()  # only the touched voxels are stored
    other = LazyGridAdam(f, lr_grid=0.1, lr_mlp=1e-3)
    other.load_state_dict(state)
    assert other.step_count == 3
    for a, b in zip(lazy.exp_avg + lazy.exp_avg_sq + lazy.last, other.exp_avg + other.exp_avg_sq + other.last):
        assert torch.equal(a, b)
    assert other.w_base == lazy.w_base and (other.w == lazy.w).all() and lazy.w.size == 4
    assert int(lazy.last[0].max()) == 3  # the step each voxel was last updated at


def test_dense_adam_state_is_refused_with_one_line():
    f = _field()
    dense = torch.optim.Adam(f.grids(), lr=0.1)
    with pytest.raises(InputError, match="dense-Adam"):
        LazyGridAdam(f, 0.1, 1e-3).load_state_dict(dense.state_dict())


def test_mlp_parameters_get_adam():
    f = _field(sh_degree=0, features=4)
    f.sparse = True
    opt = LazyGridAdam(f, 0.1, 1e-2)
    w0 = f.mlp[0].weight.detach().clone()
    sigma, x = f.query(*_points(100))
    (x.mean() + sigma.mean()).backward()
    opt.step()
    assert not torch.equal(f.mlp[0].weight, w0)


def test_dense_adam_by_default():
    f = GridField(grid_size=16, final_size=16)
    assert isinstance(make_optimizer(f, TrainConfig(dataset="unused")), torch.optim.Adam) and not f.sparse


def test_only_grids_above_the_limit_train_sparsely_and_a_grow_keeps_the_mlp_state():
    cfg = TrainConfig(dataset="unused", iters=10, lazy_above=128 ** 3)
    small = GridField(grid_size=128, final_size=129, features=2)
    dense = make_optimizer(small, cfg)
    assert isinstance(dense, torch.optim.Adam) and not small.sparse
    sigma, x = small.query(*_points(50))
    (x.mean() + sigma.mean()).backward()
    dense.step()
    mlp_state = dense.state[small.mlp[0].weight]["exp_avg"].clone()
    field, opt = _grow(small, dense, cfg, [(0, 129)], 0)
    assert isinstance(opt, LazyGridAdam) and field.sparse and field.grid_size == 129
    assert torch.equal(opt.mlp.state[field.mlp[0].weight]["exp_avg"], mlp_state)
    assert opt.step_count == 0  # the grids' state restarts


def test_occupancy_equals_thresholded_max_pooled_alpha():
    f = _field(size=40)
    with torch.no_grad():
        f.grid[0, 0] = f.grid[0, 0] * 3 - 9
    frac = f.update_occupancy(0.02)
    sigma = F.softplus(f.grid[0, 0].detach() + f.shift)
    alpha = 1 - torch.exp(-sigma * f.step_ratio * f.voxel / f.ref_voxel)
    ref = F.max_pool3d(alpha[None, None], kernel_size=3, stride=1, padding=1)[0, 0] > 0.02
    assert 0.01 < frac < 0.5 and torch.equal(f.occupancy, ref)
    with torch.no_grad():  # a single occupied blob: the box is its extent, padded by one voxel
        f.grid[0, 0] = -30.0
        f.grid[0, 0, 10:15, 20:22, 5:30] = 30.0
    f.update_occupancy(0.02)
    lo_idx, hi_idx = torch.tensor([10 - 1 - 1, 20 - 1 - 1, 5 - 1 - 1]), torch.tensor([14 + 2, 21 + 2, 29 + 2])
    assert torch.allclose(f.box, torch.stack([lo_idx, hi_idx]).float() * f.voxel - f.bound)


def test_checkpoint_packs_the_occupancy_and_restores_it(tmp_path):
    f = _field(size=20)
    with torch.no_grad():
        f.grid[0, 0] -= 4
    f.update_occupancy(0.02)
    opt = LazyGridAdam(f, 0.1, 1e-3)

    class Cfg:
        def to_json(self):
            return {}

    save_checkpoint(tmp_path / "ck.pt", f, opt, Cfg(), 1, 0.0, {})
    ck = torch.load(tmp_path / "ck.pt", weights_only=False)
    assert "occupancy" not in ck["state"] and ck["state"]["occupancy_bits"].numel() == -(-20 ** 3 // 8)
    g = field_from_checkpoint(ck, "cpu")
    assert 0 < int(f.occupancy.sum()) < f.occupancy.numel()
    assert torch.equal(g.occupancy, f.occupancy) and torch.equal(g.grid, f.grid) and torch.equal(g.box, f.box)


def test_sparse_run_resumes_bit_for_bit(dataset, tmp_path):
    """With every grid trained sparsely, a run interrupted mid-way (after the last grow, so the
    lazy optimiser's compact state is what the checkpoint carries) ends equal to an uninterrupted one."""
    a, b = tmp_path / "a", tmp_path / "b"
    cfg = _cfg(dataset, iters=50, lazy_above=1)
    train_module.train(cfg, a, progress=False, log=lambda m: None)
    train_module.train(cfg, b, progress=False, log=lambda m: None, stop_at=35)
    mid = torch.load(b / "checkpoint.pt", weights_only=False)
    assert mid["optimizer"]["kind"] == "lazy_grid_adam" and mid["optimizer"]["step"] > 0
    train_module.train(cfg, b, progress=False, log=lambda m: None)
    ca, cb = torch.load(a / "checkpoint.pt", weights_only=False), torch.load(b / "checkpoint.pt", weights_only=False)
    assert ca["iteration"] == cb["iteration"] == 50
    for key in ("grid", "sh", "occupancy_bits"):
        assert torch.equal(ca["state"][key], cb["state"][key])
    for ga, gb in zip(ca["optimizer"]["grids"], cb["optimizer"]["grids"]):
        assert torch.equal(ga["exp_avg_sq"], gb["exp_avg_sq"]) and torch.equal(ga["touched_bits"], gb["touched_bits"])


def test_sparse_reads_match_grid_sample_on_a_cropped_box():
    f = _field(size=20)
    f.crop(torch.tensor([-0.9, -0.5, -1.2]), torch.tensor([0.7, 0.8, 0.6]))
    assert len(set(f.dims)) > 1
    pts, dirs = _points(300, spread=0.45)
    dense = f.query(pts, dirs)
    f.sparse = True
    sparse = f.query(pts, dirs)
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(dense, sparse))


def test_lazy_adam_catches_a_voxel_up_on_the_steps_it_was_not_read():
    """Voxels read only now and then, with a decaying learning rate: when read, a voxel's parameter
    and moments are the dense Adam's (which moved it on its momentum while it was not read)."""
    f, ref = _field(size=10), _field(size=10)
    lazy = LazyGridAdam(f, lr_grid=0.05, lr_mlp=1e-3, betas=(0.9, 0.99))
    dense = torch.optim.Adam(ref.grids(), lr=0.05, betas=(0.9, 0.99))
    f.sparse = True
    gen = torch.Generator().manual_seed(8)
    for step in range(1, 61):
        lr = 0.05 * 0.1 ** (step / 60)
        lazy.param_groups[0]["lr"] = lr
        for g in dense.param_groups:
            g["lr"] = lr
        for i, (p, q) in enumerate(zip(f.grids(), ref.grids())):
            # the first 5 steps read everything; then each voxel is read with probability 0.15 (never
            # for the last tenth of the voxels), and at step 60 everything is read again
            C, n_vox = p.shape[1], p[0, 0].numel()
            if step <= 5 or step == 60:
                mask = torch.ones(n_vox, dtype=torch.bool)
            else:
                mask = torch.rand(n_vox, generator=gen) < 0.15
                mask[-n_vox // 10:] = False
            idx = mask.nonzero()[:, 0]
            grad = torch.randn(C, idx.numel(), generator=gen)
            vals = p.detach().view(C, -1)[:, idx].clone().requires_grad_(True)
            vals.grad = grad
            f.tape.append((p, idx, vals))
            dense_grad = torch.zeros(C, n_vox)
            dense_grad[:, idx] = grad
            q.grad = dense_grad.view_as(q)
        lazy.step()
        dense.step()
    for i, (p, q) in enumerate(zip(f.grids(), ref.grids())):
        C = p.shape[1]
        got, want = p.detach().view(C, -1), q.detach().view(C, -1)
        assert torch.allclose(got, want, rtol=1e-4, atol=1e-5), (got - want).abs().max()
        assert torch.allclose(lazy.exp_avg[i], dense.state[q]["exp_avg"].view(C, -1), rtol=1e-4, atol=1e-6)
        assert torch.allclose(lazy.exp_avg_sq[i], dense.state[q]["exp_avg_sq"].view(C, -1), rtol=1e-4, atol=1e-8)
    # without the catch-up the voxels skipped for 54 steps would be far off
    assert lazy.w.size > 1 and float(lazy.w.max()) > 0
