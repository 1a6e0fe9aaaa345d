"""The dense trainer's grid reads: values and gradients as ``grid_sample`` gives them, the gradient
added in place into ``grid.grad`` (kept between steps), the prior's block likewise."""
import torch
import torch.nn.functional as F

from spikenerf.config import TrainConfig
from spikenerf.model import GridField, _trilinear, _tv
from spikenerf.train import make_optimizer
from test_trainer_sparse import randomised


def _field(seed=0):
    """A field on a box that is not a cube, with random grids (and SH)."""
    return randomised(GridField(grid_size=12, final_size=24, sh_degree=1, aabb=[[-1.0, -0.5, -0.8], [1.2, 0.6, 0.7]],
                                dims=[14, 8, 11]), seed)


def _points(f, n=3000, seed=1):
    gen = torch.Generator().manual_seed(seed)
    lo, hi = f.aabb
    pts = lo + (hi - lo) * torch.rand(n, 3, generator=gen)
    pts[:50] = torch.maximum(torch.minimum(pts[:50].round(), hi), lo)  # some on the box's faces and corners
    return pts, F.normalize(torch.randn(n, 3, generator=gen), dim=-1)


def _reference(f, pts, dirs, up):
    """Values and gradients through ``grid_sample`` on leaf copies of the grids (autograd's way)."""
    grid = f.grid.detach().clone().requires_grad_(True)
    sh = f.sh.detach().clone().requires_grad_(True)
    vals = _trilinear(grid, f.normalise(pts), split=1)
    from spikenerf.model import sh_basis
    view = (_trilinear(sh, f.normalise(pts), split=1) * sh_basis(dirs, 1)).sum(-1)
    sigma = F.softplus(vals[:, 0] + f.shift)
    x = torch.sigmoid(vals[:, 1] + view)
    ((sigma * up[:, 0]).sum() + (x * up[:, 1]).sum()).backward()
    return sigma.detach(), x.detach(), grid.grad, sh.grad


def test_training_reads_give_grid_samples_values_and_gradients():
    f = _field()
    pts, dirs = _points(f)
    up = torch.randn(pts.shape[0], 2, generator=torch.Generator().manual_seed(2))
    sigma, x = f.query(pts, dirs)
    ((sigma * up[:, 0]).sum() + (x * up[:, 1]).sum()).backward()
    ref_sigma, ref_x, ref_grid, ref_sh = _reference(f, pts, dirs, up)
    assert torch.allclose(sigma, ref_sigma, atol=1e-5) and torch.allclose(x, ref_x, atol=1e-6)
    assert torch.allclose(f.grid.grad, ref_grid, atol=1e-5)
    assert torch.allclose(f.sh.grad, ref_sh, atol=1e-5)
    assert torch.count_nonzero(f.grid.grad) > 0.5 * f.grid.numel()  # the test reads most of the grid
    with torch.no_grad():  # evaluation reads through grid_sample: the same values
        s2, x2 = f.query(pts, dirs)
    assert torch.allclose(s2, sigma, atol=1e-5) and torch.allclose(x2, x, atol=1e-6)


def test_reads_add_into_the_gradient_that_is_there():
    f = _field()
    pts, dirs = _points(f, n=500)
    f.query(pts, dirs)[1].sum().backward()
    once = f.grid.grad.clone()
    kept = f.grid.grad
    f.query(pts, dirs)[1].sum().backward()  # a second backward adds to the same tensor
    assert f.grid.grad is kept
    assert torch.allclose(f.grid.grad, 2 * once, atol=1e-5)
    f.grid.grad.zero_()
    (f.query(pts, dirs)[1].sum() + f.query(pts, dirs)[1].sum()).backward()  # two reads in one graph
    assert torch.allclose(f.grid.grad, 2 * once, atol=1e-5)


def test_the_priors_block_gradient_is_the_slices():
    f = _field()
    ref = f.grid.detach().clone().requires_grad_(True)
    _tv(ref, 6, torch.Generator().manual_seed(4)).backward()
    tv = _tv(f.grid, 6, torch.Generator().manual_seed(4))
    tv.backward()
    assert float(tv.detach()) == float(_tv(f.grid.detach(), 6, torch.Generator().manual_seed(4)))
    assert torch.allclose(f.grid.grad, ref.grad, atol=1e-7)
    assert torch.count_nonzero(f.grid.grad) > 0


def test_a_training_step_keeps_one_gradient_buffer_and_zeroes_it():
    """As the training loop does: zero_grad(set_to_none=False), the reads add, fused Adam steps. The
    gradient stays the same tensor, and in the second step it holds that step's gradient only."""
    f = _field()
    opt = make_optimizer(f, TrainConfig(dataset="-"))
    pts, dirs = _points(f, n=800)

    def loss(field, k):
        return field.query(pts + 0.01 * k, dirs)[1].sum() + 1e-2 * field.tv_loss(torch.Generator().manual_seed(k), block=6)

    opt.zero_grad(set_to_none=False)
    loss(f, 0).backward()
    first = f.grid.grad.data_ptr()
    opt.step()
    g = _field()  # the field as the second step finds it, with no gradient yet
    with torch.no_grad():
        for a, b in zip(g.grids(), f.grids()):
            a.copy_(b)
    opt.zero_grad(set_to_none=False)
    loss(f, 1).backward()
    loss(g, 1).backward()
    assert f.grid.grad.data_ptr() == first
    assert torch.allclose(f.grid.grad, g.grid.grad, atol=1e-6) and torch.allclose(f.sh.grad, g.sh.grad, atol=1e-6)


def test_points_that_need_a_gradient_get_one():
    """A caller that differentiates through the sample points (none in the trainer) reads through
    grid_sample, whose gradient reaches the points."""
    f = _field()
    pts, dirs = _points(f, n=200)
    pts.requires_grad_(True)
    f.query(pts, dirs)[1].sum().backward()
    assert pts.grad is not None and torch.count_nonzero(pts.grad) > 0 and f.grid.grad is not None
