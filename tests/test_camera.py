"""The NeRF camera rig and the motion during exposure (pure NumPy)."""
import math

import numpy as np
import pytest

from spikegen import camera as cm


def test_look_at_is_orthonormal_and_points_at_origin():
    pose = cm.look_at(np.array([1.0, -2.0, 3.0]))
    r = pose[:3, :3]
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(r), 1.0)
    forward = -pose[:3, 2]  # cameras look down their -Z
    assert np.allclose(forward, -pose[:3, 3] / np.linalg.norm(pose[:3, 3]))
    assert pose[2, 1] > 0  # camera up has a positive world-Z component


def test_origin_projects_to_image_centre():
    pose = cm.make_views("train", 1)[0].pose
    xy = cm.project(np.zeros((1, 3)), pose, 400, 400)
    assert np.allclose(xy, [[200.0, 200.0]], atol=1e-9)
    assert math.isclose(cm.focal_px(400), 555.5555, rel_tol=1e-5)  # NeRF-synthetic focal at 400 px


@pytest.mark.parametrize("split", ["train", "val"])
def test_train_val_on_upper_hemisphere_at_nerf_radius(split):
    views = cm.make_views(split, 300, subframes=1, seed=3)
    pos = np.array([v.pose[:3, 3] for v in views])
    assert np.allclose(np.linalg.norm(pos, axis=1), cm.RADIUS)
    assert (pos[:, 2] >= 0).all()
    # uniform over the hemisphere: z uniform on [0, R] -> mean R/2, and azimuths cover all quadrants
    assert abs(pos[:, 2].mean() / cm.RADIUS - 0.5) < 0.06
    quadrants = np.histogram(np.arctan2(pos[:, 1], pos[:, 0]), bins=4, range=(-np.pi, np.pi))[0]
    assert quadrants.min() > 50


def test_test_split_is_a_circle_at_30_degrees():
    views = cm.make_views("test", 200)
    pos = np.array([v.pose[:3, 3] for v in views])
    elev = np.degrees(np.arcsin(pos[:, 2] / cm.RADIUS))
    assert np.allclose(elev, 30.0)
    az = np.unwrap(np.arctan2(pos[:, 1], pos[:, 0]))
    assert np.allclose(np.diff(az), 2 * np.pi / 200)


def test_rig_is_seeded_and_deterministic():
    a = cm.make_rig({"train": 5, "val": 5, "test": 3}, seed=0)
    b = cm.make_rig({"train": 5, "val": 5, "test": 3}, seed=0)
    c = cm.make_rig({"train": 5, "val": 5, "test": 3}, seed=1)
    assert all(np.array_equal(x.pose, y.pose) for s in a for x, y in zip(a[s], b[s]))
    assert not np.allclose(a["train"][0].pose, c["train"][0].pose)
    assert not np.allclose(a["train"][0].pose, a["val"][0].pose)  # splits draw different directions


def test_subframe_poses_orbit_symmetrically_about_the_mid_pose():
    pose = cm.make_views("val", 1)[0].pose
    subs = cm.subframe_poses(pose, 16, motion_deg=2.0)
    assert subs.shape == (16, 4, 4)
    az = np.degrees(np.arctan2(subs[:, 1, 3], subs[:, 0, 3]))
    az0 = np.degrees(np.arctan2(pose[1, 3], pose[0, 3]))
    steps = np.diff(az)
    assert np.allclose(steps, 2.0 / 16)  # sub-frame centres (k + 0.5) / K of the exposure
    assert np.isclose((az[7] + az[8]) / 2, az0)  # mid-exposure = the view's pose
    assert np.allclose(subs[:, 2, 3], pose[2, 3])  # orbit about world Z keeps the height
    odd = cm.subframe_poses(pose, 5, motion_deg=2.0)
    assert np.allclose(odd[2], pose)


def test_zero_motion_is_static():
    pose = cm.make_views("train", 1)[0].pose
    assert np.allclose(cm.subframe_poses(pose, 16, 0.0), pose[None])


def test_crop_window_holds_every_projected_point_grown_by_the_margin():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.6, 0.6, size=(500, 3))
    pose = cm.make_views("train", 1)[0].pose
    xy = cm.project(pts, pose, 400, 400)
    x0, x1, y0, y1 = cm.crop_window(pts, pose, 400, 400, margin=3)
    assert x0 <= xy[:, 0].min() - 3 and xy[:, 0].max() + 3 < x1  # x1, y1 exclusive pixel ends
    assert y0 <= xy[:, 1].min() - 3 and xy[:, 1].max() + 3 < y1
    assert x1 - x0 < xy[:, 0].ptp() + 3 + 2 * 3 and y1 - y0 < xy[:, 1].ptp() + 3 + 2 * 3  # and not much more
    # clipped to the frame, and None where that is the whole frame or a point is behind the camera
    assert cm.crop_window(pts * 2.5, pose, 400, 400, margin=3) is None
    assert cm.crop_window(pts, pose, 400, 400, margin=400) is None
    behind = np.vstack([pts, 2 * pose[:3, 3]])
    assert cm.crop_window(behind, pose, 400, 400) is None
    x0, x1, y0, y1 = cm.crop_window(pts + [0.0, 0.0, 1.9], pose, 400, 400, margin=3)
    assert y0 == 0 and y1 < 400
