"""Rendering speed and the choice of the default Cycles samples (docs/rendering.md).

    python bench/bench_render.py speed  [--scenes lego,mic] [--views 2] [--resolution 400] [--samples N] [--denoise 0/1]
                                        [--crop 1/0] [--motion DEG] [--device cpu|gpu]
    python bench/bench_render.py noise  [--scenes ...] [--samples 1,2,4,8,16] [--reference 512]
                                        [--subframes 16] [--motion 1.0] [--resolution 200] [--denoise 1,2,4]

speed: seconds per view (K = 16 sub-frames as EXR + the ground-truth PNG) at the default
settings, per scene, after the scene is built (build time printed apart); wall-clock and CPU
seconds (all threads) per view, and the load average, since a shared machine slows the wall clock;
"box area" is the mean fraction of the frame Cycles renders (the box around the object's image;
--crop 0 renders every pixel, for comparison: the files are the same bytes either way).
The first view of a scene includes Cycles' one-time set-up (BVH, kernels), so use --views >= 2.

noise: for one view per scene, the RMS error in radiance X (luminance on white) of the time
average of its K sub-frames (default motion; all share the view's noise pattern) rendered with N
samples, against the same average rendered with a high-sample reference, over the object's pixels;
next to it, the spike noise at intensity 64: the RMS error of X recovered from the full 256-frame
stream of the "paper" sensor (TFP over all frames, the sensor's maps divided out) against the
same reference, and the same for TFP over a 32-frame window (the paper's "TFP-32" baseline; a
shorter window is noisier). X is clipped to the sensor's range at intensity 64 (0..4: brighter
pixels fire every frame). The default samples is the smallest N whose render noise is below the spike noise
for every scene.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from spikegen import camera as cm
from spikegen.presets import get_sensor
from spikegen.recon import rate_to_radiance, tfp
from spikegen.render import RenderFolder, RenderJob, render_steps, rig_of, view_render_seed
from spikegen.render_blender import BlenderRenderer, RenderSettings, build_bpy_scene, builtin_renderer
from spikegen.scenes import SCENES, build_scene
from spikegen.sensor import simulate
from spikegen.spikeio import exr_to_radiance, read_exr


X_MAX = 256.0 / 64.0  # saturation at intensity 64: one spike every frame


def radiance(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(X on white [H, W] clipped to the sensor's range at intensity 64, alpha [H, W]) of a render EXR."""
    rgba = read_exr(path)
    return np.clip(exr_to_radiance(rgba) + (1.0 - rgba[:, :, 3]), 0.0, X_MAX), rgba[:, :, 3]


def speed(scenes, views: int, resolution: int, samples: int | None = None, denoise: bool | None = None,
          crop: bool = True, motion_deg: float = cm.DEFAULT_MOTION_DEG, device: str = "cpu") -> None:
    """``device`` gpu: each scene on the CPU and on the GPU side by side (one run, same views)."""
    from spikegen.render_blender import resolve_device

    given = {"samples": samples, "denoise": denoise}
    base = RenderJob("x", width=resolution, height=resolution, views=(views, 0, 0), motion_deg=motion_deg,
                     **{k: v for k, v in given.items() if v is not None})
    devices = ["cpu"] + ([resolve_device("gpu")] if device == "gpu" else [])
    print(f"# seconds per view: {base.subframes} sub-frames (EXR) + 1 PNG at {resolution} x {resolution}, "
          f"samples {base.samples} (PNG {base.png_render_samples}), denoise {base.denoise}, motion {motion_deg} deg, "
          f"{views} views per scene, {'the box around the object' if crop else 'every pixel'} rendered, "
          f"devices {', '.join(devices)}")
    print(f"# load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"{'scene':<10} {'device':<11} {'build s':>8} {'s/view':>8} {'cpu s/view':>11} {'s/image':>8} "
          f"{'box area':>9}")
    all_times = {d: [] for d in devices}
    with tempfile.TemporaryDirectory() as tmp:
        for name in scenes:
            for d in devices:
                job = dataclasses.replace(base, scene=name, device=d)
                build, per_view, cpu, area = _time_scene(job, crop, Path(tmp) / d)
                all_times[d].append((per_view, cpu))
                print(f"{name:<10} {d:<11} {build:8.2f} {per_view:8.2f} {cpu:11.2f} "
                      f"{per_view / (job.subframes + 1):8.3f} {area:9.2f}", flush=True)
    for d in devices:
        mean = np.mean(all_times[d], axis=0)
        print(f"{'mean':<10} {d:<11} {'':>8} {mean[0]:8.2f} {mean[1]:11.2f}")
    print(f"# load average after: {os.getloadavg()[0]:.2f}")


def _time_scene(job, crop: bool, tmp: Path):
    """(build s, wall s per view, CPU s per view, mean box area) of rendering ``job``'s train views."""
    t0 = time.perf_counter()
    r = builtin_renderer(job.scene, RenderSettings.for_job(job))
    if not crop:
        r.crop_points = None
    build = time.perf_counter() - t0
    folder = RenderFolder.open(tmp, job)
    views = job.views[0]
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in render_steps(folder, r):  # the path `spikegen render` takes
        pass
    per_view = (time.perf_counter() - t0) / views
    cpu = (time.process_time() - c0) / views
    full = (0, job.width, 0, job.height)
    boxes = [r.crop_box(p) or full for v in rig_of(job)["train"] for p in v.subframe_poses]
    area = np.mean([(b[1] - b[0]) * (b[3] - b[2]) for b in boxes]) / (job.width * job.height)
    return build, per_view, cpu, area


def spike_noise(x_ref: np.ndarray, mask: np.ndarray, window: int, intensity: float = 64.0,
                frames: int = 256) -> float:
    """RMS error of X recovered by TFP over ``window`` frames (centred) from the paper sensor's
    stream (its maps divided out)."""
    h, w = x_ref.shape
    sensor = get_sensor("paper", h, w, 0)
    spikes = simulate(x_ref, intensity, sensor, frames=frames, seed=1)
    x_hat = np.clip(rate_to_radiance(tfp(spikes, window), intensity, sensor), 0.0, X_MAX)
    return float(np.sqrt(np.mean((x_hat - x_ref)[mask] ** 2)))


def noise(scenes, samples_list, reference: int, resolution: int, subframes: int, motion_deg: float,
          denoised: list | None = None) -> None:
    """Columns N=...: raw renders; D=...: the same samples through the denoiser (``denoised``)."""
    denoised = denoised or []
    view = cm.make_views("train", 1, subframes, motion_deg)[0]
    print(f"# RMS error in X over object pixels of the mean of {subframes} sub-frames (motion {motion_deg} deg), "
          f"{resolution} x {resolution}, reference {reference} samples; X clipped to 0..{X_MAX:g}")
    print(f"{'scene':<10} " + " ".join(f"{'N=' + str(s):>8}" for s in samples_list)
          + "".join(f" {'D=' + str(s):>8}" for s in denoised) + f" {'TFP256@64':>10} {'TFP32@64':>9}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in scenes:
            scene, camera = build_bpy_scene(build_scene(name))
            out = {(s, False): _mean_subframes(scene, camera, view, s, resolution, Path(tmp))
                   for s in [reference, *samples_list]}
            out.update({(s, True): _mean_subframes(scene, camera, view, s, resolution, Path(tmp), True)
                        for s in denoised})
            x_ref, alpha = out[reference, False]
            mask = alpha > 0.5
            errs = [float(np.sqrt(np.mean((out[key][0] - x_ref)[mask] ** 2)))
                    for key in [(s, False) for s in samples_list] + [(s, True) for s in denoised]]
            print(f"{name:<10} " + " ".join(f"{e:8.4f}" for e in errs) + f" {spike_noise(x_ref, mask, 256):10.4f}"
                  f" {spike_noise(x_ref, mask, 32):9.4f}", flush=True)


def _mean_subframes(scene, camera, view, samples: int, resolution: int, tmp: Path, denoise: bool = False):
    """(mean X [H, W], mean alpha [H, W]) of the view's sub-frames rendered with ``samples``."""
    r = BlenderRenderer(scene, camera, RenderSettings(resolution, resolution, samples=samples, denoise=denoise))
    r.set_view_seed(view_render_seed(0, "train", 0))
    xs, alphas = [], []
    for k, pose in enumerate(view.subframe_poses):
        r.render_exr(pose, tmp / f"{samples}_{k}.exr")
        x, a = radiance(tmp / f"{samples}_{k}.exr")
        xs.append(x)
        alphas.append(a)
    return np.mean(xs, axis=0), np.mean(alphas, axis=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["speed", "noise"])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--resolution", type=int, default=None, help="default: 400 (speed), 200 (noise)")
    ap.add_argument("--samples", default=None, help="noise: list (default 1,2,4,8,16); speed: one N "
                    "(default: the render default)")
    ap.add_argument("--reference", type=int, default=512)
    ap.add_argument("--denoise", default=None, help="noise: samples to also render denoised (list, e.g. 1,2,4); "
                    "speed: 1 or 0 (default: the render default)")
    ap.add_argument("--crop", type=int, default=1, help="speed: 1 renders the box around the object (the "
                    "default for built-in scenes), 0 every pixel")
    ap.add_argument("--subframes", type=int, default=16, help="noise: sub-frames averaged (1 = one static frame)")
    ap.add_argument("--motion", type=float, default=cm.DEFAULT_MOTION_DEG, help="camera motion (deg)")
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu", help="speed: gpu also times every scene on "
                    "the first GPU backend Cycles finds, next to the CPU (an error without one)")
    a = ap.parse_args()
    a.samples_given = a.samples is not None
    a.samples = a.samples or "1,2,4,8,16"
    scenes = [s for s in a.scenes.split(",") if s]
    if a.what == "speed":
        speed(scenes, a.views, a.resolution or 400, int(a.samples) if a.samples_given else None,
              None if a.denoise is None else bool(int(a.denoise)), bool(a.crop), a.motion, a.device)
    else:
        noise(scenes, [int(s) for s in a.samples.split(",")], a.reference, a.resolution or 200, a.subframes,
              a.motion, [int(s) for s in a.denoise.split(",")] if a.denoise else [])


if __name__ == "__main__":
    from spikegen.errors import SpikegenError

    try:
        main()
    except SpikegenError as exc:
        raise SystemExit(f"bench_render: {exc}") from None
