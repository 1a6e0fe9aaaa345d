"""Forward-facing captures in normalised device coordinates (spikenerf/ndc.py): the map checked by
hand, detection, training and evaluation end to end, animations, and checkpoints that record the
space (and old ones without it, which stay in the world cube)."""
import dataclasses
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from click.testing import CliRunner  # noqa: E402

from spikegen.errors import InputError  # noqa: E402
from spikegen.formats import CaptureTransforms, SpikeBlock, ViewRecord  # noqa: E402
from spikegen.spikeio import linear_to_srgb, write_dat, write_json_atomic, write_png  # noqa: E402
from spikenerf import ndc, train as train_mod  # noqa: E402
from spikenerf.cli import main  # noqa: E402
from spikenerf.config import TrainConfig  # noqa: E402
from spikenerf.data import load_dataset  # noqa: E402
from spikenerf.eval import evaluate, reference  # noqa: E402
from spikenerf.metrics import psnr  # noqa: E402
from spikenerf.model import GridField  # noqa: E402
from spikenerf.render import render_rays  # noqa: E402
from spikenerf.train import checkpoint_space, train  # noqa: E402
from test_trainer_cli import dataset  # noqa: E402,F401 (the sphere on white: an object, not a capture)
from test_trainer_forward import (CAM_Z, CARD_Z, FRAMES, H, INTENSITY, K, SUPER, W, _poses,  # noqa: E402
                                  _spikes, make_capture)


def _turn(axis: str, degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])}[axis]


def _space(pose=None, near=2.0):
    return ndc.NDC(tuple(map(tuple, (np.eye(4) if pose is None else pose).tolist())), near, (1.5, 2.0), (0.1, -0.2),
                   ((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0)), 0.1)


def test_points_on_the_near_plane_go_to_minus_one_and_far_points_towards_one():
    sp = _space()
    # by hand: x = -1.5 X / Z + 0.1, y = -2 Y / Z - 0.2, z = 1 + 4 / Z
    np.testing.assert_allclose(sp.points(np.array([0.4, -0.6, -2.0])), [0.4, -0.8, -1.0])
    np.testing.assert_allclose(sp.points(np.array([0.4, -0.6, -4.0])), [0.25, -0.5, 0.0])
    z = sp.points(np.array([[0.0, 0.0, -d] for d in (10.0, 1e3, 1e6)]))[:, 2]
    np.testing.assert_allclose(z, [0.6, 0.996, 0.999996])
    # the same camera moved and turned: the same point in its axes has the same NDC
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = _turn("y", 30) @ _turn("x", -10), [0.5, -1.0, 3.0]
    cam = np.array([0.4, -0.6, -2.0])
    np.testing.assert_allclose(_space(pose).points(pose[:3, :3] @ cam + pose[:3, 3]), [0.4, -0.8, -1.0], atol=1e-12)


def test_the_reference_image_spans_minus_one_to_one():
    """With the capture's intrinsics (off-centre principal point), the rays through the image corners
    of the reference camera end (at infinity) on x, y = +-1: left edge -1, top edge +1."""
    a, b = (2 * K.fl_x / K.w, 2 * K.fl_y / K.h), (2 * K.cx / K.w - 1, 1 - 2 * K.cy / K.h)
    sp = ndc.NDC(tuple(map(tuple, np.eye(4).tolist())), 0.5, a, b, ((-2, -2, -1), (2, 2, 1)), 0.1)
    uv = [(0, 0), (K.w, 0), (0, K.h), (K.w, K.h)]
    d = torch.tensor([[(u - K.cx) / K.fl_x, -(v - K.cy) / K.fl_y, -1.0] for u, v in uv], dtype=torch.float64)
    o, dn, length = sp.rays(torch.zeros(4, 3, dtype=torch.float64), d / d.norm(dim=-1, keepdim=True))
    np.testing.assert_allclose(o[:, 2].numpy(), -1.0, atol=1e-12)
    np.testing.assert_allclose((o + length[:, None] * dn).numpy(), [[-1, 1, 1], [1, 1, 1], [-1, -1, 1], [1, -1, 1]],
                               atol=1e-12)


def test_rays_stay_straight_lines_and_samples_are_uniform_in_disparity():
    rng = np.random.default_rng(0)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = _turn("x", 20), [0.2, 0.1, -0.3]
    sp = _space(pose, near=1.5)
    o = rng.uniform(-0.3, 0.3, (16, 3))
    d = np.stack([rng.uniform(-0.4, 0.4, 16), rng.uniform(-0.4, 0.4, 16), -np.ones(16)], -1)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)) @ pose[:3, :3].T  # forward of the reference camera
    o_w = o @ pose[:3, :3].T + pose[:3, 3]
    o_ndc, d_ndc, length = (v.numpy() for v in sp.rays(torch.as_tensor(o_w), torch.as_tensor(d)))
    np.testing.assert_allclose(o_ndc[:, 2], -1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(d_ndc, axis=1), 1.0)
    for i in range(16):
        t = np.array([0.5, 1.0, 3.0, 10.0, 1e3, 1e7]) + (1.5 + o[i, 2]) / -(d[i] @ pose[:3, 2])
        p = sp.points(o_w[i] + t[:, None] * d[i])
        s = (p - o_ndc[i]) @ d_ndc[i]  # where each point lies along the NDC ray
        np.testing.assert_allclose(o_ndc[i] + s[:, None] * d_ndc[i], p, atol=1e-9)  # on it: a straight line
        assert (np.diff(s) > 0).all() and s[-1] < length[i] and s[-1] == pytest.approx(length[i], rel=1e-6)
    # uniform steps along the NDC ray are uniform steps in disparity: the world points they map back to
    # (on the ray, at reference depth -Z = 2 n / (1 - z)) have equally spaced 1 / depth
    s = np.linspace(0.0, 0.9, 7) * length[0]
    z = o_ndc[0, 2] + s * d_ndc[0, 2]
    depth = 2 * 1.5 / (1 - z)
    t = (depth + o[0, 2]) / -(d[0] @ pose[:3, 2])  # the world ray's parameter at that reference depth
    np.testing.assert_allclose(sp.points(o_w[0] + t[:, None] * d[0]), o_ndc[0] + s[:, None] * d_ndc[0], atol=1e-9)
    np.testing.assert_allclose(np.diff(1 / depth), (1 / depth[1] - 1 / depth[0]))


def test_a_ray_that_does_not_point_forward_finds_nothing():
    sp = _space()
    o, d, length = sp.rays(torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
    assert (length == 0).all()
    field = GridField(grid_size=8, final_size=8, bound=1.0)
    with torch.no_grad():
        field.grid[:, 0] = 50.0  # opaque everywhere
    x, acc = render_rays(field, o, d, background=0.0, near=0.0)
    assert (acc == 0).all() and (x == 0).all()


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_capture(tmp_path_factory.mktemp("capture"))


def test_the_capture_is_forward_facing_with_the_near_plane_of_its_bounds(capture):
    ds = load_dataset(capture)
    space, why = ndc.for_dataset(ds)
    assert space is not None and "forward-facing" in why
    c = np.array([v.pose[:3, 3] for v in ds.splits["train"]])
    np.testing.assert_allclose(np.array(space.pose)[:3, :3], np.eye(3), atol=1e-12)  # all look down -z
    np.testing.assert_allclose(np.array(space.pose)[:3, 3], c.mean(0))
    # every bound is 0.9 (CAM_Z - CARD_Z) in front of its camera, a camera further back (larger z) than
    # the mean centre puts it nearer to the reference camera
    assert space.near == pytest.approx(min(0.9 * (CAM_Z - CARD_Z) - (c[:, 2] - c[:, 2].mean())))
    lo, hi = space.box
    assert lo[2] == -1 and hi[2] == 1 and lo[0] < -1 and hi[0] > 1 and lo[1] < -1 and hi[1] > 1


def _edit(capture, tmp_path, change):
    doc = json.loads((capture / "transforms_train.json").read_text())
    change(doc)
    (tmp_path / "train").symlink_to(capture / "train")
    write_json_atomic(tmp_path / "transforms_train.json", doc)
    return tmp_path


def test_views_facing_other_ways_keep_the_world_cube(capture, tmp_path):
    def turn(doc):
        for f in doc["frames"][::3]:
            m = np.array(f["transform_matrix"])
            m[:3, :3] = _turn("y", 90) @ m[:3, :3]
            f["transform_matrix"] = m.tolist()
    (tmp_path / "turned").mkdir()
    ds = load_dataset(_edit(capture, tmp_path / "turned", turn))
    space, why = ndc.for_dataset(ds)
    assert space is None and "not forward-facing" in why, why
    assert float(why.split("optical axis is ")[1].split(" degrees")[0]) > ndc.MAX_AXIS_DEG  # said, and above
    run = tmp_path / "run"
    msgs = []
    train(TrainConfig(dataset=str(ds.root), iters=2, device="cpu", batch_rays=64, space="auto"), run,
          progress=False, log=msgs.append)
    assert any("not forward-facing" in m and "stays in the world cube" in m for m in msgs)
    assert "space" not in torch.load(run / "checkpoint.pt", weights_only=False)


def test_a_capture_without_bounds_is_not_ndc(capture, tmp_path):
    def drop(doc):
        for f in doc["frames"]:
            f.pop("near"), f.pop("far")
    space, why = ndc.for_dataset(load_dataset(_edit(capture, tmp_path, drop)))
    assert space is None and "near/far" in why


def _cfg(capture, **kw):
    base = dict(dataset=str(capture), iters=200, device="cpu", batch_rays=1024, grid_start=16, grid_final=48,
                occupancy_after=50, space="ndc")
    base.update(kw)
    return TrainConfig(**base)


def test_ndc_training_evaluates_and_renders_end_to_end(capture, tmp_path):
    run = tmp_path / "run"
    msgs = []
    train(_cfg(capture), run, progress=False, log=msgs.append)
    assert any("rays in NDC" in m for m in msgs)
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    space = checkpoint_space(ck)
    assert ck["space"]["kind"] == "ndc" and space == ndc.for_dataset(load_dataset(capture))[0]
    lo, hi = ck["field"]["aabb"]
    assert lo[2] == -1.0 and hi[2] == pytest.approx(1.0) and lo[0] == pytest.approx(space.box[0][0])  # float32
    m = evaluate(run, device="cpu", progress=False)
    ds = load_dataset(capture)
    refs = [linear_to_srgb(reference(ds, v, H, W)[1]) for v in ds.splits["test"]]
    constant = float(np.mean(refs))
    baseline = float(np.mean([psnr(np.full_like(r, constant), r) for r in refs]))
    assert m["compared_with"] == "reconstruction" and m["psnr"] > baseline + 6.0, (m["psnr"], baseline)
    res = CliRunner().invoke(main, ["render", str(run), "--path", "spiral", "--frames", "3", "--device", "cpu",
                                    "--out", str(tmp_path / "a.gif"), "--quiet"])
    assert res.exit_code == 0 and (tmp_path / "a.gif").is_file(), res.output


def test_ndc_space_round_trips_through_json_and_a_resumed_run_is_bit_identical(capture, tmp_path):
    space = ndc.for_dataset(load_dataset(capture))[0]
    assert ndc.NDC.from_json(json.loads(json.dumps(space.to_json()))) == space
    a, b = tmp_path / "a", tmp_path / "b"
    cfg = _cfg(capture, iters=80, occupancy_after=20, occupancy_every=10)
    train(cfg, a, progress=False, log=lambda m: None)
    train(cfg, b, progress=False, log=lambda m: None, stop_at=30)
    train(cfg, b, progress=False, log=lambda m: None)
    ca, cb = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (a, b))
    assert ca["space"] == cb["space"] and ca["iteration"] == cb["iteration"] == 80
    for key in ("grid", "sh", "aabb"):
        assert torch.equal(ca["state"][key], cb["state"][key]), key


def test_a_checkpoint_from_before_ndc_resumes_and_evaluates_in_the_world_cube(capture, tmp_path, monkeypatch):
    """A run of a forward-facing capture made before NDC existed (no "space" key, the world cube) goes
    on in the cube when resumed now, ending as an uninterrupted cube run does, bit for bit."""
    cfg = _cfg(capture, iters=60, occupancy_after=20, occupancy_every=10, space="auto")
    old, whole = tmp_path / "old", tmp_path / "whole"
    with monkeypatch.context() as mp:  # the trainer as it was: no NDC
        mp.setattr(train_mod.ndc, "for_dataset", lambda ds: (None, "before NDC"))
        train(cfg, whole, progress=False, log=lambda m: None)
        train(cfg, old, progress=False, log=lambda m: None, stop_at=25)
    assert "space" not in torch.load(old / "checkpoint.pt", weights_only=False)
    msgs = []
    train(cfg, old, progress=False, log=msgs.append)  # resumed by today's trainer
    assert any("resuming" in m for m in msgs)
    co, cw = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (old, whole))
    assert "space" not in co and co["field"]["aabb"] == cw["field"]["aabb"] == [[-1.5] * 3, [1.5] * 3]
    assert torch.equal(co["state"]["grid"], cw["state"]["grid"])
    assert evaluate(old, device="cpu", progress=False)["psnr"] == evaluate(whole, device="cpu", progress=False)["psnr"]


def test_the_cube_on_request_and_ndc_is_refused_where_it_does_not_apply(capture, dataset, tmp_path):
    """With --space cube a forward capture trains in the world cube; NDC asked for an object on white,
    or for a run whose checkpoint is in the cube, is one clear error, no run."""
    msgs = []
    train(_cfg(capture, iters=2, space="cube"), tmp_path / "cube", progress=False, log=msgs.append)
    assert "space" not in torch.load(tmp_path / "cube" / "checkpoint.pt", weights_only=False)
    assert not any("NDC" in m for m in msgs)
    with pytest.raises(InputError, match="not an object on white"):
        train(TrainConfig(dataset=str(dataset), iters=2, device="cpu", space="ndc"), tmp_path / "w", progress=False,
              log=lambda m: None)
    assert not (tmp_path / "w").exists()
    with pytest.raises(InputError, match="checkpoint was made with space='cube'"):
        train(_cfg(capture, iters=4), tmp_path / "cube", progress=False, log=lambda m: None)  # ndc on a cube run


def _sky_capture(root, views: int = 20):
    """As test_trainer_forward.make_capture, but behind the card there is only sky: a bright luminance
    that depends on the ray's direction alone (content at infinity, as a far background is in NDC)."""
    rng = np.random.default_rng(7)
    s = (np.arange(SUPER) + 0.5) / SUPER
    col = np.arange(W)[None, :, None, None] + s[None, None, None, :]
    row = np.arange(H)[:, None, None, None] + s[None, None, :, None]
    records = []
    for i, pose in enumerate(_poses(views, rng)):
        d = np.stack(np.broadcast_arrays((col - K.cx) / K.fl_x, -(row - K.cy) / K.fl_y, -np.ones(1)), -1)
        d = d @ pose[:3, :3].T
        t = (CARD_Z - pose[2, 3]) / d[..., 2]
        xc, yc = pose[0, 3] + t * d[..., 0], pose[1, 3] + t * d[..., 1]
        card = (np.abs(xc - 0.15) < 0.25) & (np.abs(yc + 0.05) < 0.2)
        sky = 0.8 + 0.3 * d[..., 0] / np.linalg.norm(d, axis=-1)
        spikes = _spikes(np.where(card, 0.3, sky).mean(axis=(2, 3)), rng)
        write_dat(root / f"train/r_{i}.dat", spikes)
        write_png(root / f"train/r_{i}.png", linear_to_srgb(np.clip(spikes.mean(0) / spikes.mean(0).max(), 0, 1)))
        records.append(ViewRecord("train", i, pose, pose[None]))
    bounds = np.tile([0.9 * (CAM_Z - CARD_Z), 1e3], (views, 1))
    doc = CaptureTransforms(K, SpikeBlock(H, W, FRAMES, 1, INTENSITY, background=None), tuple(records), bounds,
                            tuple(f"v{i:02d}.dat" for i in range(views)), np.eye(4), "tfp")
    write_json_atomic(root / "transforms_train.json", doc.to_json())
    return root


def test_the_light_that_passes_through_the_grid_takes_the_luminance_at_infinity(tmp_path, monkeypatch):
    """A card in front of a bright sky at infinity, trained in NDC: with the opaque sample at each
    ray's point at infinity (ndc.NDC.opaque_infinity, the default) the held-out views score well
    above the same training without it (the light that passes through the grid then adds black, and
    the sky must first be learned opaque in the grid's far layers); its checkpoint records it."""
    cap = _sky_capture(tmp_path / "sky")
    cfg = _cfg(cap, iters=150)
    train(cfg, tmp_path / "with", progress=False, log=lambda m: None)
    real = ndc.for_dataset
    monkeypatch.setattr(train_mod.ndc, "for_dataset",
                        lambda ds: (dataclasses.replace(real(ds)[0], opaque_infinity=False), "without"))
    train(cfg, tmp_path / "without", progress=False, log=lambda m: None)
    monkeypatch.undo()
    assert torch.load(tmp_path / "with" / "checkpoint.pt", weights_only=False)["space"]["opaque_infinity"] is True
    assert checkpoint_space(torch.load(tmp_path / "without" / "checkpoint.pt", weights_only=False)).opaque_infinity \
        is False
    with_, without = (evaluate(tmp_path / r, device="cpu", progress=False)["psnr"] for r in ("with", "without"))
    assert with_ > without + 3.0, (with_, without)


def test_a_space_saved_before_the_opaque_infinity_reads_without_it():
    old = {k: v for k, v in _space().to_json().items() if k != "opaque_infinity"}  # as checkpoints held it
    assert ndc.NDC.from_json(old) == _space() and not _space().opaque_infinity
    on = dataclasses.replace(_space(), opaque_infinity=True)
    assert ndc.NDC.from_json(json.loads(json.dumps(on.to_json()))) == on


def test_auto_is_the_default_ndc_for_a_forward_capture_the_cube_for_an_object_on_white(capture, dataset, tmp_path):
    """Without flags a forward-facing capture trains in NDC and a synthetic object on white in the world
    cube; a run made in the cube with --space cube resumes under the default in the cube."""
    assert TrainConfig(dataset="x").space == "auto"
    res = CliRunner().invoke(main, ["train", str(capture), "--iters", "2", "--batch-rays", "64", "--device", "cpu",
                                    "--out", str(tmp_path / "fwd"), "--quiet"])
    assert res.exit_code == 0, res.output
    assert torch.load(tmp_path / "fwd" / "checkpoint.pt", weights_only=False)["space"]["kind"] == "ndc"
    res = CliRunner().invoke(main, ["train", str(dataset), "--iters", "2", "--batch-rays", "64", "--device", "cpu",
                                    "--out", str(tmp_path / "obj"), "--quiet"])
    assert res.exit_code == 0, res.output
    ck = torch.load(tmp_path / "obj" / "checkpoint.pt", weights_only=False)
    assert "space" not in ck and ck["field"]["aabb"] == [[-1.5] * 3, [1.5] * 3]
    train(_cfg(capture, iters=4, space="cube"), tmp_path / "cube", progress=False, log=lambda m: None, stop_at=2)
    msgs = []
    train(_cfg(capture, iters=4, space="auto"), tmp_path / "cube", progress=False, log=msgs.append)
    ck = torch.load(tmp_path / "cube" / "checkpoint.pt", weights_only=False)
    assert any("resuming" in m for m in msgs) and ck["iteration"] == 4 and "space" not in ck


@pytest.mark.parametrize("k1", [0.2, -0.1])
def test_the_grid_box_holds_every_pixel_ray_through_a_radial_lens(capture, tmp_path, monkeypatch, k1):
    from spikenerf.render import pixel_rays

    def lens(doc):
        doc.update(camera_model="OPENCV", k1=k1)

    ds = load_dataset(_edit(capture, tmp_path, lens))
    space, why = ndc.for_dataset(ds)
    assert space is not None, why
    lo, hi = np.array(space.box[0][:2]), np.array(space.box[1][:2])
    h, w = ds.height, ds.width
    cam = ds.camera(h, w)
    assert cam[4] == k1
    pix = torch.arange(h * w)
    outside_corners = 0
    corner_space = None
    if k1 > 0:  # the box the lens's four corner rays alone give: too small, a pincushion bends the edges out
        with monkeypatch.context() as mp:
            mp.setattr(ndc, "EDGE_POINTS", 2)  # each edge's two ends: the corners
            corner_space = ndc.for_dataset(ds)[0]
    for v in ds.splits["train"]:
        pose = torch.as_tensor(v.pose, dtype=torch.float64)
        o, d = pixel_rays(pose.expand(h * w, 4, 4), pix, h, w, cam)
        o_ndc, d_ndc, length = space.rays(o, d)
        ends = torch.cat([o_ndc, o_ndc + length[:, None] * d_ndc]).numpy()[:, :2]
        assert (ends >= lo - 1e-9).all() and (ends <= hi + 1e-9).all()
        if corner_space is not None:
            clo, chi = np.array(corner_space.box[0][:2]), np.array(corner_space.box[1][:2])
            outside_corners += int(((ends < clo - 1e-9) | (ends > chi + 1e-9)).any(axis=1).sum())
    if k1 > 0:
        assert outside_corners > 0
