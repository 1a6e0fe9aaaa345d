"""Structure-from-motion option variants on an imported capture's images, scored against the truth.

    python bench/bench_sfm_options.py DATASET --truth render.json VARIANT [VARIANT ...]

DATASET: a folder ``spikegen import`` wrote (its ``train/r_<i>.png`` are the images SfM reads; view i
is render.json's i-th train view). Each VARIANT is a ``+``-joined list of changes to the importer's
own options (``spikegen.importer._sfm_options``, so ``base`` is exactly what ``spikegen import``
runs); the poses found are normalised as the import does and compared with the truth as
bench/bench_import.py does (both alignments; ``rot*``: orientations alone). Used to choose the
import's settings on a capture other than the one the benchmark reports (docs/real_captures.md).

Changes: ``reprojX`` (the mapper's filter and the triangulator's merge and complete reprojection
errors, px), ``filtX`` (the mapper's filter alone), ``guided`` (guided matching), ``affine`` (SIFT
affine shapes), ``feat16k`` (16384 SIFT features), ``ransac1`` (two-view RANSAC error 1 px),
``twoview`` (keep two-view tracks), ``tri1`` (triangulation and filter angles 0.5 degree),
``tightba`` (global bundle adjustment to tolerance 1e-10, 200 iterations, 20 refinements),
``truefocal`` (the renderer's focal length, fixed) / ``truefocalref`` (as a start, refined),
``final`` / ``finalfixk`` (one more global bundle adjustment at the end, 500 iterations,
tolerances 1e-12; ``fixk``: intrinsics fixed).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from spikegen import camera as cm
from spikegen import importer as im


def options(pycolmap, changes: set, size: tuple[int, int]):
    ex, ma, ve, mp = im._sfm_options(pycolmap)
    reader = pycolmap.ImageReaderOptions(camera_model=im.CAMERA_MODELS[im.DEFAULT_CAMERA_MODEL])
    for c in sorted(changes, key=lambda c: not c.startswith("reproj")):  # reprojX first, then filtX
        if c.startswith("reproj"):
            r = float(c[6:])
            mp.mapper.filter_max_reproj_error = r
            mp.triangulation.merge_max_reproj_error = mp.triangulation.complete_max_reproj_error = r
        elif c.startswith("filt"):
            mp.mapper.filter_max_reproj_error = float(c[4:])
    if "guided" in changes:
        ma.guided_matching = True
    if "affine" in changes:
        ex.sift.estimate_affine_shape = True
    if "feat16k" in changes:
        ex.sift.max_num_features = 16384
    if "ransac1" in changes:
        ve.ransac.max_error = 1.0
    if "twoview" in changes:
        mp.triangulation.ignore_two_view_tracks = False
    if "tri1" in changes:
        mp.mapper.filter_min_tri_angle = mp.triangulation.min_angle = 0.5
    if "tightba" in changes:
        mp.ba_global_function_tolerance, mp.ba_global_max_num_iterations = 1e-10, 200
        mp.ba_global_max_refinements, mp.ba_global_max_refinement_change = 20, 1e-6
    if changes & {"truefocal", "truefocalref"}:
        reader.camera_params = f"{cm.focal_px(size[0])},{size[0] / 2},{size[1] / 2}"
        if "truefocal" in changes:
            mp.ba_refine_focal_length = mp.mapper.abs_pose_refine_focal_length = False
    return ex, ma, ve, mp, reader


def reconstruct(pycolmap, image_dir: Path, names: list, changes: set, size):
    pycolmap.logging.minloglevel = pycolmap.logging.Level.ERROR.value
    pycolmap.set_random_seed(im.SFM_SEED)
    ex, ma, ve, mp, reader = options(pycolmap, changes, size)
    with tempfile.TemporaryDirectory(prefix="bench-sfm-") as work:
        db = Path(work) / "database.db"
        pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ex, device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(db, matching_options=ma, verification_options=ve, device=pycolmap.Device.cpu)
        models = pycolmap.incremental_mapping(db, image_dir, Path(work) / "sparse", mp)
    rec = max(sorted(models.items()), key=lambda kv: kv[1].num_reg_images())[1]
    if changes & {"final", "finalfixk"}:
        o = pycolmap.BundleAdjustmentOptions()
        o.print_summary = False
        so = o.ceres.solver_options
        so.num_threads, so.max_num_iterations = 1, 500
        so.function_tolerance = so.gradient_tolerance = so.parameter_tolerance = 1e-12
        if "finalfixk" in changes:
            o.refine_focal_length = o.refine_extra_params = False
        pycolmap.bundle_adjustment(rec, o)
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--truth", required=True, type=Path)
    ap.add_argument("variants", nargs="+")
    args = ap.parse_args()
    pycolmap = im._pycolmap()
    doc = json.loads((args.dataset / "transforms_train.json").read_text())
    size = (doc["w"], doc["h"])
    truth_all = np.array([f["transform_matrix"] for f in json.loads(args.truth.read_text())["splits"]["train"]])
    image_dir = args.dataset / "train"
    names = sorted((p.name for p in image_dir.glob("r_*.png")), key=lambda n: int(n[2:-4]))
    print(f"{'variant':26} {'reg':>5} {'fl_x':>6} | centres: rot ctr % | full pose: rot ctr % | rot* | points "
          f"reproj px | s")
    for variant in args.variants:
        t0 = time.perf_counter()
        changes = set(variant.split("+")) - {"base"}
        rec = reconstruct(pycolmap, image_dir, names, changes, size)
        res = im.sfm_result(rec, names)
        est = im.apply_normalisation(im.normalise(res.c2w_gl, res.points), res.c2w_gl)
        truth = truth_all[[int(n[2:-4]) for n in res.names]]
        e = im.pose_errors(est, truth, float(np.median(np.linalg.norm(truth[:, :3, 3], axis=1))))
        med = {k: float(np.median(v)) for k, v in e.items() if k.endswith(("_deg", "_frac"))}
        print(f"{variant:26} {len(res.names):2d}/{len(names):<2d} {res.intrinsics.fl_x:6.1f} | "
              f"{med['rotation_deg']:.3f} {100 * med['centre_frac']:.3f} | {med['rotation_full_deg']:.3f} "
              f"{100 * med['centre_full_frac']:.3f} | {med['rotation_own_deg']:.3f} | {rec.num_points3D():5d} "
              f"{rec.compute_mean_reprojection_error():.3f} | {time.perf_counter() - t0:.0f}", flush=True)


if __name__ == "__main__":
    main()
