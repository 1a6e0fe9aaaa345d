"""Error-guided rays (trainer/spikenerf/errorrays.py): the tiles cover every pixel once, the map finds
where the error hides, the draws follow the map, and the sums do not depend on the rays' order."""
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from spikenerf.errorrays import FLOOR, REFRESH, SCALE_BITS, ErrorRays, tile_size  # noqa: E402


def _tiles(er, height, width):
    return er.tile_of.reshape(height, width)


def test_tiles_cover_every_pixel_once_on_a_size_the_tile_does_not_divide():
    er = ErrorRays(2, 7, 251, 0.5, "cpu")  # tiles of 2 x 2 pixels; the last row and column of tiles are cut
    assert tile_size(251) == 2 and tile_size(400) == 4 and tile_size(100) == 1 and tile_size(40) == 1
    tiles = _tiles(er, 7, 251)
    assert er.tiles == 4 * 126 and int(er.count.sum()) == 7 * 251
    assert torch.equal(torch.sort(er.order).values, torch.arange(7 * 251))  # every pixel once
    assert tiles[0, 0] == tiles[1, 1] and tiles[0, 1] != tiles[0, 2]
    assert int(er.count[tiles[6, 250]]) == 1 and int(er.count[tiles[6, 248]]) == 2 and int(er.count[0]) == 4
    for t in (0, 7, int(tiles[6, 0])):  # a tile's pixels are those the order lists from its start
        listed = er.order[er.start[t]: er.start[t] + er.count[t]]
        assert torch.equal(torch.sort(listed).values, torch.nonzero(tiles.reshape(-1) == t).reshape(-1))


def test_the_error_of_a_ray_is_its_squared_error_over_its_prediction():
    er = ErrorRays(1, 10, 10, 0.5, "cpu")
    pred, obs = torch.tensor([1.0, 0.05, 0.001]), torch.tensor([1.2, 0.15, 0.011])
    er.note(torch.zeros(3, dtype=torch.long), torch.tensor([0, 1, 2]), pred, obs)
    got = er.sums[:3].double() / 2 ** SCALE_BITS
    want = (pred - obs).double().square() / pred.double().clamp(min=FLOOR)
    assert torch.allclose(got, want, rtol=0, atol=2.0 ** -SCALE_BITS)
    # a dim pixel off by 0.1 weighs more than a bright one off by 0.2: a count's noise grows with its mean
    assert got[1] > got[0]


def test_the_map_finds_where_the_error_hides_and_the_draws_follow_it():
    """A hidden 8 x 8 block of image 2 of 3 (40 x 40 each) where the field is wrong; elsewhere it is right
    up to a little noise. After one refresh the drawn rays land in the block as often as its share of the
    map says, and a draw of the block's tiles covers every pixel of them."""
    H = W = 40
    er = ErrorRays(3, H, W, 0.5, "cpu")
    gen = torch.Generator().manual_seed(1)
    hidden = torch.zeros(3, H, W, dtype=torch.bool)
    hidden[2, 20:28, 5:13] = True
    img = torch.arange(3).repeat_interleave(H * W).repeat(2)
    pix = torch.arange(H * W).repeat(6)
    pred = torch.full((img.numel(),), 0.5)
    obs = pred + 0.01 * torch.randn(img.numel(), generator=gen)
    obs[hidden.reshape(-1).repeat(2)] += 0.4
    assert er.rays(2048) == 0  # nothing is drawn from the map before its first refresh
    for it in range(REFRESH):
        if it == 0:
            er.note(img, pix, pred, obs)
        er.step_done(it)
    assert er.rays(2048) == 1024
    im, px = er.draw(200_000, torch.Generator().manual_seed(2))
    in_block = hidden[im, px // W, px % W].double().mean()
    weights = er.error.reshape(3, H, W)
    share = float(weights[hidden].sum() / weights.sum())
    assert share > 0.95 and abs(float(in_block) - share) < 0.005
    drawn = torch.zeros(3, H * W, dtype=torch.bool)
    drawn[im, px] = True
    assert drawn.reshape(3, H, W)[hidden].all()


def test_sums_do_not_depend_on_the_order_of_the_rays():
    er1, er2 = ErrorRays(2, 16, 16, 0.3, "cpu"), ErrorRays(2, 16, 16, 0.3, "cpu")
    gen = torch.Generator().manual_seed(3)
    img, pix = torch.randint(0, 2, (5000,), generator=gen), torch.randint(0, 256, (5000,), generator=gen)
    pred, obs = torch.rand(5000, generator=gen), torch.rand(5000, generator=gen)
    er1.note(img, pix, pred, obs)
    p = torch.randperm(5000, generator=gen)
    er2.note(img[p], pix[p], pred[p], obs[p])
    assert torch.equal(er1.sums, er2.sums) and torch.equal(er1.hits, er2.hits)


def test_state_round_trip_draws_the_same():
    er = ErrorRays(2, 20, 20, 0.5, "cpu")
    gen = torch.Generator().manual_seed(4)
    for it in range(REFRESH + 7):  # a refresh, then sums pending
        img, pix = torch.randint(0, 2, (64,), generator=gen), torch.randint(0, 400, (64,), generator=gen)
        er.note(img, pix, torch.rand(64, generator=gen), torch.rand(64, generator=gen))
        er.step_done(it)
    again = ErrorRays(2, 20, 20, 0.5, "cpu")
    again.load_state_dict(er.state_dict())
    assert torch.equal(again.sums, er.sums) and torch.equal(again.hits, er.hits) and torch.equal(again.cdf, er.cdf)
    a, b = er.draw(100, torch.Generator().manual_seed(5)), again.draw(100, torch.Generator().manual_seed(5))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    with pytest.raises(ValueError, match="tiles"):
        ErrorRays(3, 20, 20, 0.5, "cpu").load_state_dict(er.state_dict())
    with pytest.raises(ValueError):
        ErrorRays(1, 4, 4, 1.0, "cpu")


def test_weights_keep_the_loss_unbiased():
    """A step's rays drawn from the mixture (uniform with 1 - F, the map with F) and weighted by
    ErrorRays.weights average a per-pixel loss to its mean over all pixels; unweighted they would not."""
    H = W = 20
    er = ErrorRays(2, H, W, 0.5, "cpu")
    gen = torch.Generator().manual_seed(6)
    img = torch.arange(2).repeat_interleave(H * W)
    pix = torch.arange(H * W).repeat(2)
    pred = torch.full((img.numel(),), 0.5)
    obs = pred + 0.3 * (torch.rand(img.numel(), generator=gen) < 0.1)  # a tenth of the pixels are wrong
    er.note(img, pix, pred, obs)
    er.refresh()
    loss = (pred - obs).square().reshape(2, H * W).double()  # what each pixel's ray would add to the loss
    n, k = 400_000, 200_000
    draw = torch.Generator().manual_seed(7)
    u_img, u_pix = torch.randint(0, 2, (n - k,), generator=draw), torch.randint(0, H * W, (n - k,), generator=draw)
    m_img, m_pix = er.draw(k, draw)
    i, p = torch.cat([u_img, m_img]), torch.cat([u_pix, m_pix])
    w = er.weights(i, p, k / n).double()
    assert float(w.max()) <= 2.0 + 1e-6  # at most 1 / (1 - F)
    exact = float(loss.mean())
    weighted, unweighted = float((loss[i, p] * w).mean()), float(loss[i, p].mean())
    assert abs(weighted - exact) < 0.03 * exact and unweighted > 4 * exact
