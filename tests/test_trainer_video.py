"""spikenerf render: camera paths, depth from the renderer, and animations of two grey spheres off
the centre (so the view changes as the camera orbits): put in a field directly (fast), and
learned from their spike streams by a tiny training run (slow)."""
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from click.testing import CliRunner  # noqa: E402
from PIL import Image  # noqa: E402

from spikegen.camera import FAR, RADIUS, look_at  # noqa: E402
from spikegen.spikeio import write_json_atomic, write_png  # noqa: E402
from spikenerf.cli import main  # noqa: E402
from spikenerf.model import GridField  # noqa: E402
from spikenerf.render import render_image, render_rays  # noqa: E402
from spikenerf.train import (CHECKPOINT, TrainConfig, field_from_checkpoint, make_optimizer,  # noqa: E402
                             save_checkpoint, train)
from spikenerf.video import GAP_PX, camera_radius, depth_colours, path_poses  # noqa: E402

SIZE = 32
ANGLE_X = 0.6911112070083618
SPHERES = [((0.55, 0.0, 0.0), 0.45, 0.3), ((-0.45, 0.35, 0.25), 0.4, 0.75)]  # centre, radius, grey


def _first_hit(origin, dirs):
    """Distance ``[n]`` to the nearest sphere along unit rays (inf: none) and its grey ``[n]``."""
    t_best, grey = np.full(len(dirs), np.inf), np.zeros(len(dirs))
    for centre, r, g in SPHERES:
        oc = origin - np.asarray(centre)
        b = dirs @ oc
        disc = b * b - (oc @ oc - r * r)
        t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
        near = t < t_best
        t_best, grey = np.where(near, t, t_best), np.where(near, g, grey)
    return t_best, grey


def _pixel_dirs(pose, size=SIZE):
    focal = 0.5 * size / math.tan(0.5 * ANGLE_X)
    j, i = np.mgrid[0:size, 0:size] + 0.5
    d_cam = np.stack([(i - size / 2) / focal, -(j - size / 2) / focal, -np.ones_like(i)], -1).reshape(-1, 3)
    d = d_cam @ pose[:3, :3].T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _spheres_png(path, pose):
    t, grey = _first_hit(pose[:3, 3], _pixel_dirs(pose))
    rgba = np.zeros((SIZE * SIZE, 4))
    rgba[:, :3] = grey[:, None]
    rgba[:, 3] = np.isfinite(t)
    write_png(path, rgba.reshape(SIZE, SIZE, 4))


def _hemisphere_pose(k):
    az, el = 0.7 * k, math.radians(10 + 9 * (k % 7))
    return look_at(RADIUS * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]))


def _transforms(folder, spike: bool):
    """transforms_train.json with the 24 cameras of :func:`_hemisphere_pose`: of a NeRF-synthetic
    scene, or (``spike``) of a spike dataset without spike files (rendering reads only the cameras)."""
    meta = {"camera_angle_x": ANGLE_X,
            "frames": [{"file_path": f"./train/r_{k}", "transform_matrix": _hemisphere_pose(k).tolist()}
                       for k in range(24)]}
    if spike:
        meta["spike"] = {"height": SIZE, "width": SIZE, "frames": 256, "intensity": 64, "format": "dat"}
    write_json_atomic(folder / "transforms_train.json", meta)
    return folder


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A run folder holding the spheres themselves as a field (opaque inside, their greys), saved
    as training saves: what is rendered is then known exactly, and no training is needed."""
    dataset = _transforms(tmp_path_factory.mktemp("ds"), spike=True)
    G = 48
    field = GridField(grid_size=G, final_size=G, sh_degree=0)
    axis = np.linspace(-field.bound, field.bound, G)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")  # grid [x, y, z] (grid_sample reads (z, y, x))
    density, grey = np.full(x.shape, -30.0), np.full(x.shape, 0.5)
    for centre, r, g in SPHERES:
        inside = (x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2 <= r * r
        density[inside], grey[inside] = 30.0, g
    with torch.no_grad():
        field.grid[0, 0] = torch.as_tensor(density)
        field.grid[0, 1] = torch.as_tensor(np.log(grey / (1 - grey)))
        solid = torch.as_tensor(density > 0)[None, None].float()
        field.occupancy = torch.nn.functional.max_pool3d(solid, 3, 1, 1)[0, 0] > 0  # one voxel of margin
    cfg = TrainConfig(dataset=str(dataset), sh_degree=0)
    out = tmp_path_factory.mktemp("run") / "spheres"
    focal = 0.5 * SIZE / math.tan(0.5 * ANGLE_X)
    save_checkpoint(out / CHECKPOINT, field, make_optimizer(field, cfg), cfg, 0, 0.0,
                    {"height": SIZE, "width": SIZE, "focal_px": focal, "intensity": 64.0})
    return out


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """A field trained briefly from the spike streams of the spheres (spikegen convert, then train)."""
    from spikegen.dataset import convert

    src = _transforms(tmp_path_factory.mktemp("spheres"), spike=False)
    for k in range(24):
        _spheres_png(src / f"train/r_{k}.png", _hemisphere_pose(k))
    (folder,) = convert(src, tmp_path_factory.mktemp("ds"), [64], sensor="paper", progress=False)
    out = tmp_path_factory.mktemp("run") / "trained"
    cfg = TrainConfig(dataset=str(folder), iters=200, device="cpu", batch_rays=1024, grid_start=16, grid_final=32,
                      occupancy_after=20, occupancy_every=10)
    train(cfg, out, progress=False, log=lambda m: None)
    return out


def _render(args):
    res = CliRunner().invoke(main, ["render", *map(str, args), "--device", "cpu", "--quiet"])
    return res.exit_code, res.stdout, res.stderr


def _gif_frames(path):
    with Image.open(path) as im:
        frames = []
        for k in range(im.n_frames):
            im.seek(k)
            frames.append(np.asarray(im.convert("RGB"), dtype=np.int16))
    return frames


# ---------------------------------------------------------------------- paths (no training)
def test_orbit_is_the_test_circle():
    poses = path_poses("orbit", 8, RADIUS)
    c = poses[:, :3, 3]
    assert poses.shape == (8, 4, 4)
    np.testing.assert_allclose(np.linalg.norm(c, axis=1), RADIUS)
    np.testing.assert_allclose(np.degrees(np.arcsin(c[:, 2] / RADIUS)), 30.0)
    np.testing.assert_allclose(np.degrees(np.arctan2(c[:, 1], c[:, 0])) % 360, np.arange(8) * 45.0, atol=1e-9)
    forward = -poses[:, :3, 2]  # cameras look down their -z: at the origin
    np.testing.assert_allclose(forward, -c / RADIUS, atol=1e-12)


def test_spiral_turns_twice_while_rising_and_closing_in():
    poses = path_poses("spiral", 16, 4.0)
    c = poses[:, :3, 3]
    dist = np.linalg.norm(c, axis=1)
    el = np.degrees(np.arcsin(c[:, 2] / dist))
    assert el[0] == pytest.approx(10.0) and el[8] == pytest.approx(50.0) and el.min() == pytest.approx(10.0)
    assert dist[0] == pytest.approx(4.0) and dist[8] == pytest.approx(3.4) and dist.min() == pytest.approx(3.4)
    az = np.radians(np.arange(16) * 45.0)  # 720 degrees over 16 frames
    np.testing.assert_allclose(c[:, :2] / np.linalg.norm(c[:, :2], axis=1, keepdims=True),
                               np.stack([np.cos(az), np.sin(az)], axis=1), atol=1e-12)


def test_depth_from_the_renderer_on_an_opaque_cube():
    f = GridField(grid_size=33, final_size=33, bound=1.5)
    with torch.no_grad():
        f.grid[0, 0] = -30.0
        f.grid[0, 0, 11:22, 11:22, 11:22] = 30.0  # an opaque cube, faces at about |x| = 0.5
    o = torch.tensor([[0.0, 0.0, 4.0], [1.2, 1.2, 4.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    with torch.no_grad():
        x, acc, depth = render_rays(f, o, d, far=6.0)
        x2, acc2 = render_rays(f, o, d)  # without far: as before
    assert acc[0] == pytest.approx(1.0, abs=1e-4) and depth[0] == pytest.approx(3.5, abs=0.1)
    assert acc[1] == pytest.approx(0.0, abs=1e-4) and depth[1] == pytest.approx(6.0, abs=1e-3)  # miss: at far
    assert torch.equal(x, x2) and torch.equal(acc, acc2)


def test_depth_colours_run_from_yellow_to_purple():
    c = depth_colours(np.array([[1.0, 2.0, 4.0, 6.0, 9.0]]))
    assert c.dtype == np.uint8 and c.shape == (1, 5, 3)
    assert c[0, 0].tolist() == c[0, 1].tolist() == [253, 231, 37]  # at and nearer than near
    assert c[0, 3].tolist() == c[0, 4].tolist() == [68, 1, 84]  # at and beyond far
    assert c[0, 2].tolist() == [33, 145, 140]


def test_camera_radius_of_a_dataset_or_the_default(run, tmp_path):
    dataset = torch.load(run / CHECKPOINT, weights_only=False)["config"]["dataset"]
    assert camera_radius(dataset) == pytest.approx(RADIUS)
    msgs = []
    assert camera_radius(tmp_path / "gone", log=msgs.append) == RADIUS
    assert "gone" in msgs[0] and str(RADIUS) in msgs[0]


# ---------------------------------------------------------------------- the trained field
def _render_maps(run, pose):
    ck = torch.load(run / CHECKPOINT, weights_only=False)
    field = field_from_checkpoint(ck, "cpu").eval()
    maps = render_image(field, torch.as_tensor(pose, dtype=torch.float32), SIZE, SIZE, ck["focal_px"], far=FAR)
    t_true, _ = _first_hit(pose[:3, 3], _pixel_dirs(pose))
    return (*(m.numpy() for m in maps), t_true.reshape(SIZE, SIZE))


def test_depth_is_the_distance_to_the_spheres(run):
    pose = path_poses("orbit", 1, RADIUS)[0]
    _, acc, depth, t_true = _render_maps(run, pose)
    hit = np.isfinite(t_true)
    solid, empty = acc > 0.99, acc < 0.01
    assert 50 < hit.sum() < SIZE * SIZE - 300
    assert np.mean(solid[hit]) > 0.9 and np.mean(empty[~hit]) > 0.95  # opaque where the spheres are
    assert np.median(np.abs(depth[solid & hit] - t_true[solid & hit])) < 0.05  # voxels are 0.064
    np.testing.assert_allclose(depth[empty], FAR, atol=0.1)  # nothing on the ray: at far


@pytest.mark.slow
def test_trained_field_is_near_where_opacity_is_high(trained_run, tmp_path):
    pose = path_poses("orbit", 1, RADIUS)[0]
    _, acc, depth, t_true = _render_maps(trained_run, pose)
    solid, empty = acc > 0.9, acc < 0.1
    assert solid.sum() > 50 and empty.sum() > 300
    assert np.median(depth[solid]) < 4.5 < np.median(depth[empty])
    assert np.mean(np.isfinite(t_true[solid])) > 0.9  # opaque where the spheres are
    hit = solid & np.isfinite(t_true)  # there, about the right distance (final voxels are 0.097)
    assert np.median(np.abs(depth[hit] - t_true[hit])) < 0.3
    out = tmp_path / "trained.gif"
    code, _, stderr = _render([trained_run, "--frames", "4", "--out", out])
    assert code == 0, stderr
    lum = [f[:, :SIZE, 0] for f in _gif_frames(out)]
    assert len(lum) == 4 and min(np.abs(a - b).mean() for a, b in zip(lum, lum[1:])) > 2.0


def test_render_orbit_gif(run, tmp_path):
    out = tmp_path / "orbit.gif"
    code, stdout, stderr = _render([run, "--path", "orbit", "--frames", "6", "--out", out])
    assert code == 0, stderr
    assert "6 frames" in stdout
    frames = _gif_frames(out)
    assert len(frames) == 6
    assert frames[0].shape == (SIZE, 3 * SIZE + 2 * GAP_PX, 3)
    lum = [f[:, :SIZE, 0] for f in frames]
    moved = [np.abs(a - b).mean() for a, b in zip(lum, lum[1:] + lum[:1])]
    assert min(moved) > 2.0, moved  # every step of the orbit changes the view
    assert np.all(frames[0][:, SIZE:SIZE + GAP_PX] == 255)  # panels apart by white columns
    with Image.open(out) as im:
        assert im.info["duration"] == 50 and im.info["loop"] == 0  # --fps 20 by default
    again = tmp_path / "again.gif"
    assert _render([run, "--path", "orbit", "--frames", "6", "--out", again])[0] == 0
    assert again.read_bytes() == out.read_bytes()  # reproducible bit for bit
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.gif", "orbit.gif"]  # no temporaries left


def test_render_spiral_mp4(run, tmp_path):
    ffmpeg = pytest.importorskip("imageio_ffmpeg")
    out = tmp_path / "spiral.mp4"
    code, _, stderr = _render([run, "--path", "spiral", "--frames", "4", "--fps", "8", "--out", out])
    assert code == 0, stderr
    reader = ffmpeg.read_frames(str(out))
    meta = next(reader)
    assert sum(1 for _ in reader) == 4
    assert tuple(meta["size"]) == (3 * SIZE + 2 * GAP_PX, SIZE) and meta["fps"] == 8
    again = tmp_path / "again.mp4"
    assert _render([run, "--path", "spiral", "--frames", "4", "--fps", "8", "--out", again])[0] == 0
    assert again.read_bytes() == out.read_bytes()  # reproducible bit for bit


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize("case,args,needle", [
    ("no checkpoint", ["{empty}", "--out", "{out}/a.gif"], "checkpoint.pt"),
    ("unknown path", ["{run}", "--path", "helix", "--out", "{out}/a.gif"], "helix"),
    ("no frames", ["{run}", "--frames", "0", "--out", "{out}/a.gif"], "--frames"),
    ("bad suffix", ["{run}", "--out", "{out}/a.avi"], "a.avi"),
    ("zero fps", ["{run}", "--fps", "0", "--out", "{out}/a.gif"], "--fps"),
])
def test_bad_input_is_one_line_and_writes_nothing(run, tmp_path, case, args, needle):
    empty, out = tmp_path / "empty", tmp_path / "out"
    empty.mkdir()
    code, _, stderr = _render([a.format(run=run, empty=empty, out=out) for a in args])
    assert code != 0
    assert len(stderr.splitlines()) == 1 and needle in stderr and "Traceback" not in stderr, stderr
    assert not out.exists() and list(empty.iterdir()) == []


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_cuda_without_a_gpu_is_one_line(run, tmp_path):
    res = CliRunner().invoke(main, ["render", str(run), "--out", str(tmp_path / "a.gif"), "--device", "cuda"])
    assert res.exit_code != 0
    assert len(res.stderr.splitlines()) == 1 and "no CUDA device" in res.stderr
    assert list(tmp_path.iterdir()) == []
