"""Training settings: a plain dataclass (no torch), so the command line takes its defaults from it."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .methods import DEFAULT_METHOD


SPACES = ("cube", "auto", "ndc")  # TrainConfig.space
COMPARE_WITH = ("auto", "truth", "reconstruction")  # spikenerf eval --compare-with (eval.reference)
RAY_ORDERS = ("uniform", "shuffled")  # TrainConfig.ray_order (rayorder.py)
TV_LUMINANCE = ("logit", "floored", "linear", "srgb", "off")  # TrainConfig.tv_luminance (model.GridField.tv_loss)

# The default iteration count at two image sizes, chosen on the project's procedural lego (spikelik,
# i64, 48 train views, scored on its 8 val views; docs/trainer.md "Iterations"), never on the real
# lego's views: the best measured count at 100 x 100 and at 400 x 400. Between them it is
# interpolated in log pixels; outside, the nearer one holds.
ITERS_AT = ((100 * 100, 3000), (400 * 400, 9000))
# in training, samples a ray reaches with less transmittance than this are not rendered (Instant-NGP's
# early ray termination threshold; render.visible_samples): what they could add to a pixel is below it,
# and so is the gradient they give the samples in front; on trained 400 x 400 lego fields they are a
# third to two fifths of the occupied samples (docs/trainer.md, "Early ray termination"). 0 renders
# every occupied sample; checkpoints from before the option count as 0.
STOP_TRANSMITTANCE = 1e-4


COARSE_FACTOR = 4  # --coarse-to-fine: the first part of the run sees the images this many times smaller a side


def default_iters(height: int, width: int) -> int:
    """``--iters 0``: the iterations for an image of this size (ITERS_AT), a multiple of 100."""
    (p0, n0), (p1, n1) = ITERS_AT
    t = min(1.0, max(0.0, math.log(height * width / p0) / math.log(p1 / p0)))
    return int(round(n0 * (n1 / n0) ** t / 100)) * 100


@dataclass(frozen=True)
class TrainConfig:
    dataset: str
    method: str = DEFAULT_METHOD
    iters: int = 0  # 0 = chosen from the image size (default_iters)
    device: str = "auto"
    resolution: int = 0  # 0 = the dataset's
    frames: int | None = None  # train from the first w frames of each stream; None = all (resolved when training)
    windows: int = 0  # count windows per view of a moving camera; 0 = as few as keep each window's image
    #                   motion within targets.MAX_WINDOW_BLUR_PX (targets.count_windows; resolved when training)
    sensor_maps: str = ""  # a sensor file whose R and dark current replace the dataset's (e.g. a calibration)
    # what a count method read from each window, "count" or "interval" (targets.count_statistic): resolved
    # from the method and the dataset's sensor when training, recorded, not chosen ("" until then)
    statistic: str = ""
    seed: int = 0
    batch_rays: int = 2048
    lr_grid: float = 0.1
    lr_mlp: float = 2e-3
    lr_decay: float = 0.1  # the learning rates decay exponentially to this fraction of their start over the run
    adam_eps: float = 1e-8  # Adam's eps for the voxel grids (the MLP keeps 1e-8)
    error_rays: float = 0.0  # the fraction of each step's rays drawn where the error is high (errorrays.py)
    ray_order: str = "uniform"  # uniform: drawn independently; shuffled: each ray once an epoch (rayorder.py)
    # the fraction of the iterations trained on the images box-downsampled by COARSE_FACTOR (at that size's grid
    # schedule) before the rest at full size (train.grid_schedule); 0 = full size throughout
    coarse_to_fine: float = 0.0
    grid_start: int = 32
    grid_final: int = 0  # 0 = chosen from the image size
    # the sample step along a ray in voxels of the current grid (model.GridField.step_ratio)
    step_ratio: float = 0.5
    upsample_at: tuple = (0.1, 0.2, 0.3)  # fractions of iters at which the grid grows
    fit_box: bool = True  # at each growth (from occupancy_after on) crop the grid to the occupied box first
    occupancy_every: int = 50
    occupancy_after: int = 100  # no pruning before this iteration (empty space must first be learned)
    occupancy_threshold: float = 2e-2
    tv_weight: float = 1e-4
    # > 0: each ray's likelihood term weighted by the sRGB slope at its luminance over that at grey, squared, at
    # most this (train.display_weight); 0 = off; None = the method's default (methods.default_srgb_weight: 400 for
    # the likelihood methods where a white pixel counts at least 16 spikes a window, else 0), or a resumed run's own
    srgb_weight: float | None = None
    tv_luminance: str = "logit"  # what the prior compares of the luminance (TV_LUMINANCE; model.GridField.tv_loss)
    stop_transmittance: float = STOP_TRANSMITTANCE  # early ray termination in training; 0 = none
    lazy_above: int = 0  # grids with more voxels than this train with the lazy Adam (optim.py); 0 = never
    # the field's space for a scene that fills the frame: "cube" (world [-1.5, 1.5]^3), "ndc" (LLFF's
    # normalised device coordinates; refused unless the views face one way), "auto" (NDC where it applies,
    # the cube otherwise; objects on white always train in the cube)
    space: str = "auto"
    tv_points: int = 0  # > 0: the prior at the voxels of this many of a step's sample points, not on a random block
    sh_degree: int = 1  # view-dependent luminance: spherical harmonics up to this degree (0 = none)
    sh_scale: int = 2  # the SH coefficients' grid is this many times coarser than the main grid
    checkpoint_every_s: float = 30.0
    checkpoint_every: int = 500  # iterations (whichever comes first)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["upsample_at"] = list(self.upsample_at)
        return d
