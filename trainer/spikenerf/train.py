"""Training loop: seeded, checkpointed, resumable, device-agnostic.

Every iteration draws its rays from a ``torch.Generator`` seeded by ``(seed, iteration)``, so
a run resumed from a checkpoint continues with exactly the rays an uninterrupted run uses.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from spikegen.errors import InputError, SpikegenError
from spikegen.spikeio import atomic_path, remove_stale_parts, write_json_atomic

from . import ndc, neuron
from .config import COARSE_FACTOR, RAY_ORDERS, SPACES, TrainConfig, default_iters
from .data import load_dataset
from .errorrays import ErrorRays
from .methods import METHODS, SRGB_LEAST_COUNT, default_srgb_weight, white_count
from .model import SRGB_SLOPE_AT_GREY, GridField, linear_to_srgb, srgb_slope
from .optim import LazyGridAdam
from .rayorder import shuffled_rays
from .render import BACKGROUND, pixel_rays, render_ndc_rays, render_rays
from .targets import Targets, build_targets, count_windows

CHECKPOINT = "checkpoint.pt"


class TrainError(SpikegenError):
    """Training cannot go on (e.g. the loss became NaN)."""

    exit_code = 4


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available (use --device auto or cpu)")
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device must be auto, cpu or cuda, got {name!r}")
    return torch.device(name)


def final_grid(cfg: TrainConfig, width: int) -> int:
    return cfg.grid_final or int(min(256, max(32, round(1.28 * width / 8) * 8)))


def coarse_until(cfg: TrainConfig) -> int:
    """The first iteration at full size (``--coarse-to-fine``; 0 when the whole run is at full size)."""
    return int(cfg.coarse_to_fine * cfg.iters)


def grid_schedule(cfg: TrainConfig, width: int) -> list[tuple[int, int]]:
    """[(iteration, grid size)]: sizes growing geometrically from grid_start to the final size. With
    ``--coarse-to-fine``: over its coarse iterations the schedule of a run of that many iterations on images
    ``COARSE_FACTOR`` times smaller (its own final size), then one growth to the final size where the full-size
    images start."""
    until = coarse_until(cfg)
    if until > 0:
        coarse = dataclasses.replace(cfg, iters=until, coarse_to_fine=0.0, grid_final=0)
        return grid_schedule(coarse, width // COARSE_FACTOR) + [(until, final_grid(cfg, width))]
    G = final_grid(cfg, width)
    n = len(cfg.upsample_at)
    sizes = [int(round(cfg.grid_start * (G / cfg.grid_start) ** ((i + 1) / n))) for i in range(n)]
    return [(int(f * cfg.iters), s) for f, s in zip(cfg.upsample_at, sizes)]


def make_field(cfg: TrainConfig, width: int, space: ndc.NDC | None = None) -> GridField:
    """The cube ``[-1.5, 1.5]^3`` in world units; with ``space``, its NDC box, sized as the cube
    ``[-1, 1]^3`` would be (``grid_start`` points across [-1, 1], cubic voxels, the box's upper
    corner moved out to the next whole voxel)."""
    common = dict(grid_size=cfg.grid_start, final_size=final_grid(cfg, width), sh_degree=cfg.sh_degree,
                  sh_scale=cfg.sh_scale, step_ratio=cfg.step_ratio)
    if space is None:
        return GridField(**common)
    lo, hi = np.array(space.box)
    voxel = 2.0 / (cfg.grid_start - 1)
    dims = [int(math.ceil((h - l) / voxel - 1e-6)) + 1 for l, h in zip(lo, hi)]
    aabb = [lo.tolist(), (lo + voxel * (np.array(dims) - 1)).tolist()]
    return GridField(**common, bound=1.0, aabb=aabb, dims=dims)


def make_optimizer(field: GridField, cfg: TrainConfig):
    """Above ``cfg.lazy_above`` voxels (when set): lazy Adam over the grids (only the voxels a step
    read are updated, caught up on the steps they missed; optim.py), the field in sparse mode so
    that it records those reads. Otherwise PyTorch's fused dense Adam."""
    field.sparse = cfg.lazy_above > 0 and field.grid[0, 0].numel() > cfg.lazy_above
    if field.sparse:
        return LazyGridAdam(field, cfg.lr_grid, cfg.lr_mlp, betas=(0.9, 0.99), eps=cfg.adam_eps)
    return torch.optim.Adam([{"params": field.grids(), "lr": cfg.lr_grid, "eps": cfg.adam_eps},
                             {"params": field.mlp.parameters(), "lr": cfg.lr_mlp}], betas=(0.9, 0.99), fused=True)


def learning_rate_factor(it: int, iters: int, final: float = 0.1) -> float:
    """Exponential decay to ``final`` (``--lr-decay``) of the start over the run."""
    return final ** (it / max(1, iters))


class Batch:
    """Device tensors of the targets and ray sampling for one iteration."""

    def __init__(self, tg: Targets, device: torch.device):
        self.tg = tg
        self.poses = torch.from_numpy(tg.poses).to(device)
        self.values = torch.from_numpy(tg.values).to(device)
        self.frames = torch.from_numpy(tg.frames).to(device)
        self.resp = torch.from_numpy(tg.resp).to(device)
        self.dark = torch.from_numpy(tg.dark).to(device)
        self.device = device
        if tg.kind == "paper":  # the published fixed-pattern maps (Nl, Nd, D_light) [P]
            self.paper_maps = neuron.paper_fpn_maps(self.resp, self.dark, tg.lux_to_rate)

    def draw(self, n: int, gen: torch.Generator, mined: ErrorRays | None = None,
             shuffled: tuple[int, int] | None = None):
        """Image and pixel indices ``[n]`` and sample offsets ``[n]``, drawn on the CPU from ``gen``
        (so every device draws the same) and then moved to the run's device, and the rays' weights ``[n]``
        in the loss (None: all 1). With ``mined`` (``--error-rays``) the last ``mined.rays(n)`` rays are drawn
        from its error map, the others uniformly, and the weights undo what the map adds to a ray's chance
        (ErrorRays.weights). With ``shuffled = (iteration, seed)`` (``--ray-order shuffled``) the rays are the
        iteration's ``n`` places of the run's seeded order, every ray once an epoch (rayorder.py), not drawn
        independently."""
        N, P = self.values.shape
        k = mined.rays(n) if mined is not None else 0
        if shuffled is None:
            img, pix = torch.randint(0, N, (n - k,), generator=gen), torch.randint(0, P, (n - k,), generator=gen)
        else:  # (``gen`` does not draw these, so the jitter below is not what it is in a uniform draw)
            flat = shuffled_rays(shuffled[0] * n, n - k, N * P, shuffled[1])
            img, pix = torch.div(flat, P, rounding_mode="floor"), flat % P
        jitter, weights = torch.rand(n, generator=gen), None
        if k:
            image, pixel = mined.draw(k, gen)
            img, pix = torch.cat([img, image]), torch.cat([pix, pixel])
            weights = mined.weights(img, pix, k / n)
        if self.device.type == "cuda":  # from page-locked memory, without waiting for the device
            def move(t):
                return t.pin_memory().to(self.device, non_blocking=True)
        else:
            def move(t):
                return t.to(self.device)
        return move(img), move(pix), move(jitter), (None if weights is None else move(weights))


def display_weight(x: torch.Tensor, most: float) -> torch.Tensor:
    """``--srgb-weight``: each ray's weight in the likelihood, the squared slope of the sRGB encoding at its
    rendered luminance ``x`` (detached) over the slope at mid-grey, at most ``most``. An error of the rendered
    luminance then weighs about as it does on a display, where evaluation measures it: 385 times a grey one's
    below X = 0.0031 (the encoding's linear part), 0.45 times at white."""
    return (srgb_slope(x.detach().clamp(0, 1)) / SRGB_SLOPE_AT_GREY).square().clamp(max=most)


def method_loss(method, x, img, pix, batch: Batch, intensity: float, weights: torch.Tensor | None = None,
                srgb_weight: float = 0.0):
    """(loss, prediction, observation): the last two ``[n]`` in comparable units (radiance-like; for
    ``spikenerf-paper`` the gamma-encoded rate of its targets), for the progress bar's PSNR. ``weights``
    ``[n]``: the rays' weights in the mean (``--error-rays``: ErrorRays.weights), else 1. ``srgb_weight`` > 0
    (``--srgb-weight``, the likelihood methods only): each term also weighted by :func:`display_weight`."""
    def mean(terms):
        return terms.mean() if weights is None else (terms * weights).mean()

    obs = batch.values[img, pix]
    if batch.tg.kind == "radiance":
        if method.loss == "srgb":
            return mean((linear_to_srgb(x) - linear_to_srgb(obs)).square()), x, obs
        return mean((x - obs).square()), x, obs
    if batch.tg.kind == "paper":
        pred = neuron.paper_pixel(x, intensity, *(m[pix] for m in batch.paper_maps))
        return mean((pred - obs).square()), pred, obs
    tg, frames = batch.tg, batch.frames[img]
    if method.exact_sensor and tg.sensor_kind == "rsir":
        lam = neuron.rsir_rate(x, intensity, batch.resp[pix], batch.dark[pix])
    else:
        lam = neuron.spike_rate(x, intensity, batch.resp[pix], batch.dark[pix])
    mu = neuron.expected_count(lam, frames, tg.reset if method.exact_sensor else "subtract")
    to_x = 256.0 / (intensity * frames)  # count -> radiance-like units, for comparable loss scales
    if method.loss == "nll":
        exact = method.exact_sensor
        var = neuron.count_variance(mu.detach(), tg.electrons if exact else 0.0,
                                    jitter=tg.threshold_jitter if exact else 0.0)
        terms = (mu - obs).square() / (6.0 * var) * to_x.square()
        loss = mean(terms if srgb_weight <= 0 else terms * display_weight(x, srgb_weight))
    else:
        loss = mean(((mu - obs) * to_x).square())
    return loss, mu * to_x, obs * to_x


def iteration_generator(seed: int, it: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed) * 1_000_003 + int(it))


def save_checkpoint(path: Path, field, opt, cfg, it, train_s, extra) -> None:
    """Everything a bit-identical resume needs: the grids in full, the occupancy as bits, the
    optimizer's moments of the voxels it has touched (LazyGridAdam.state_dict)."""
    field_state = field.state_dict()
    occupancy = field_state.pop("occupancy")
    field_state["occupancy_bits"] = torch.from_numpy(np.packbits(occupancy.cpu().numpy().reshape(-1)))
    state = {"config": cfg.to_json(), "field": field.config(), "state": field_state,
             "optimizer": opt.state_dict(), "iteration": it, "train_seconds": train_s, **extra}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path, device) -> dict:
    try:
        return torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # a corrupt checkpoint: say which file
        raise InputError(f"{path}: not a readable checkpoint ({exc.__class__.__name__})") from None


def field_from_checkpoint(ck: dict, device) -> GridField:
    field = GridField(**ck["field"]).to(device)
    state = dict(ck["state"])
    state.setdefault("aabb", field.aabb)  # checkpoints from before the fitted box: the cube
    if "occupancy_bits" in state:  # stored packed by save_checkpoint (older checkpoints hold the bool grid)
        shape = field.occupancy.shape
        bits = np.unpackbits(state.pop("occupancy_bits").cpu().numpy(), count=field.occupancy.numel())
        state["occupancy"] = torch.from_numpy(bits.astype(bool).reshape(shape)).to(device)
    field.load_state_dict(state)
    return field


def checkpoint_space(ck: dict) -> ndc.NDC | None:
    """The space a checkpoint's field lies in: its :class:`ndc.NDC`, or None for world coordinates
    (checkpoints without the key, all of those from before NDC existed, are in world coordinates)."""
    space = ck.get("space")
    return ndc.NDC.from_json(space) if space else None


def checkpoint_camera(ck: dict) -> tuple:
    """(height, width, focal, background) a checkpoint was trained with: ``focal`` a float or
    ``(fl_x, fl_y, cx, cy)`` (render.pixel_rays); checkpoints from before backgrounds were recorded
    were trained on white."""
    focal = ck["focal_px"]
    focal = tuple(float(v) for v in focal) if isinstance(focal, (tuple, list)) else float(focal)
    return int(ck["height"]), int(ck["width"]), focal, float(ck.get("background", BACKGROUND))


def _check_resume(ck: dict, cfg: TrainConfig, path: Path, legacy: tuple[int, int]) -> None:
    """``legacy``: (frames, windows) of a checkpoint from before those keys existed. Checkpoints from
    before SH was added have no SH keys: they are degree 0 (the scale is then moot); those from before
    --frames used every frame of the stream, those from before --windows the method's fixed count, those
    from before ``statistic`` the counts."""
    all_frames, legacy_windows = legacy
    old = {"sh_degree": 0, "sh_scale": TrainConfig.sh_scale, "frames": all_frames, "sensor_maps": "",
           "fit_box": False, "lazy_above": 0, "space": "cube", "windows": legacy_windows, "lr_grid": 0.1, "lr_decay": 0.1,
           "adam_eps": 1e-8, "error_rays": 0.0, "coarse_to_fine": 0.0, "tv_luminance": "logit", "ray_order": "uniform",
           "srgb_weight": 0.0, "stop_transmittance": 0.0, "step_ratio": 0.5, "statistic": "count", **ck["config"]}
    new = cfg.to_json()
    for key in ("dataset", "method", "resolution", "seed", "batch_rays", "lr_grid", "lr_decay", "adam_eps",
                "error_rays", "ray_order", "coarse_to_fine", "tv_luminance", "srgb_weight", "stop_transmittance",
                "grid_start", "grid_final", "step_ratio", "upsample_at",
                "sh_degree", "sh_scale", "frames", "windows", "statistic", "sensor_maps", "fit_box", "lazy_above"):
        if old.get(key) != new.get(key):
            raise InputError(f"{path}: checkpoint was made with {key}={old.get(key)!r}, this run asks "
                             f"{new.get(key)!r}; use another --out or the same settings")
    # the space: a resumed run keeps its checkpoint's; "auto" takes it, "cube" and "ndc" must name it
    made_in = "ndc" if ck.get("space") else "cube"
    if new["space"] != "auto" and new["space"] != made_in:
        raise InputError(f"{path}: checkpoint was made with space={old['space']!r} (its field is in "
                         f"{'NDC' if made_in == 'ndc' else 'the world cube'}), this run asks {new['space']!r}; "
                         f"use another --out or the same settings")


def train(cfg: TrainConfig, out: Path, progress: bool = True, log=print, stop_at: int | None = None) -> Path:
    """Train and write ``out/checkpoint.pt`` (+ ``out/config.json``); resumes if a checkpoint is there.

    ``stop_at``: end this session after that iteration (with a checkpoint), as an interruption would.
    """
    if cfg.method not in METHODS:
        raise InputError(f"unknown --method {cfg.method!r}; expected one of {', '.join(METHODS)}")
    if cfg.iters < 0:
        raise InputError(f"--iters must be >= 0 (0 = chosen from the image size), got {cfg.iters}")
    device = resolve_device(cfg.device)
    method = METHODS[cfg.method]
    ds = load_dataset(cfg.dataset)
    H, W = _resolution(ds, cfg.resolution)
    # the fitted box is for an object on white; a scene that fills the frame (an imported capture) keeps its box
    if cfg.windows < 0:
        raise InputError(f"--windows must be >= 0 (0 = chosen from the camera's motion), got {cfg.windows}")
    if not 0 <= cfg.coarse_to_fine < 1:
        raise InputError(f"--coarse-to-fine must be in [0, 1), got {cfg.coarse_to_fine}")
    if cfg.coarse_to_fine > 0 and (H % COARSE_FACTOR or W % COARSE_FACTOR or W // COARSE_FACTOR < 8):
        raise InputError(f"--coarse-to-fine: the training images' {W} x {H} must shrink {COARSE_FACTOR} times a side "
                         f"to at least 8 pixels across")
    if cfg.ray_order not in RAY_ORDERS:
        raise InputError(f"--ray-order {cfg.ray_order!r}: expected one of {', '.join(RAY_ORDERS)}")
    if cfg.ray_order == "shuffled" and cfg.error_rays > 0:
        raise InputError("--ray-order shuffled visits every ray once an epoch; --error-rays draws some where the "
                         "error is high: use one of them")
    if cfg.srgb_weight is not None and not cfg.srgb_weight >= 0:
        raise InputError(f"--srgb-weight must be >= 0 (0 = off), got {cfg.srgb_weight}")
    if cfg.srgb_weight and method.loss != "nll":
        raise InputError(f"--srgb-weight is for the likelihood methods (spikelik, spikelik-count), not {cfg.method}")
    if cfg.tv_points and cfg.tv_luminance != "logit":
        raise InputError("--tv-luminance is for the block prior; --tv-points compares the stored values")
    asked_windows = cfg.windows
    cfg = dataclasses.replace(cfg, frames=_frames(ds, cfg.frames), fit_box=cfg.fit_box and not ds.fills_frame,
                              iters=cfg.iters or default_iters(H, W))
    windows = count_windows(ds, method, H, W, cfg.frames, cfg.windows)
    counts = white_count(ds.intensity, cfg.frames, windows, (ds.width // W) ** 2)
    weight = default_srgb_weight(cfg.method, counts) if cfg.srgb_weight is None else float(cfg.srgb_weight)
    made = _checkpoint_config(out)  # the config.json of a checkpoint to resume from, else None
    if made is not None and asked_windows == 0:  # a run made under an earlier rule (targets.MAX_WINDOW_BLUR_PX)
        windows = _keep(out, _positive_int(made.get("windows")), windows, lambda n: f"{n} count windows", log)
    if made is not None and cfg.srgb_weight is None:  # a run made before the default changed (before the key: off)
        weight = _keep(out, float(made.get("srgb_weight", 0.0)), weight, lambda w: f"--srgb-weight {w:g}", log)
    elif cfg.srgb_weight is None and default_srgb_weight(cfg.method) != weight:
        log(f"{ds.root}: a white pixel counts {counts:.3g} spikes a count window, fewer than {SRGB_LEAST_COUNT:g}: "
            f"training without the sRGB weight (--srgb-weight 0; docs/trainer.md \"The weight needs counts\")")
    cfg = dataclasses.replace(cfg, windows=windows, srgb_weight=weight)
    if ds.heldout != "test":
        log(f"{ds.root}: no test split; evaluating on {ds.heldout} ({len(ds.splits['test'])} views)")
    if device.type == "cuda" and cfg.batch_rays == TrainConfig.batch_rays:
        log(f"on a GPU a step of many more rays costs about what one of {cfg.batch_rays} does: --batch-rays 32768 "
            "trains faster (docs/trainer.md, \"Measured on a GPU, third lease\")")
    space = None  # the world cube (an object on white, --space cube, or views that do not all face one way)
    if cfg.space not in SPACES:
        raise InputError(f"unknown space {cfg.space!r}; one of {', '.join(SPACES)}")
    if cfg.space == "ndc" and not ds.fills_frame:
        raise InputError(f"{ds.root}: --space ndc is for a scene that fills the frame, not an object on white")
    if cfg.space != "cube" and ds.fills_frame:  # NDC if its views all look one way
        space, why = ndc.for_dataset(ds)
        if space is None and cfg.space == "ndc":
            raise InputError(f"{ds.root}: --space ndc: {why}")
        log(f"{ds.root}: {why}" + ("" if space else "; the field stays in the world cube [-1.5, 1.5]^3"))
    tg = build_targets(ds, method, H, W, progress=progress, frames=cfg.frames, maps_file=cfg.sensor_maps or None,
                       windows=cfg.windows)
    coarse = None  # --coarse-to-fine: ((its targets, their height, width, camera), first full-size iteration)
    if coarse_until(cfg) > 0:
        h, w = H // COARSE_FACTOR, W // COARSE_FACTOR
        tc = build_targets(ds, method, h, w, progress=progress, frames=cfg.frames, maps_file=cfg.sensor_maps or None,
                           windows=count_windows(ds, method, h, w, cfg.frames, asked_windows))
        coarse = ((Batch(tc, device), h, w, ds.camera(h, w)), coarse_until(cfg))
    cfg = dataclasses.replace(cfg, statistic=tg.statistic)
    if cfg.windows > 1:
        log(f"{ds.root}: the counts of each moving view in {cfg.windows} windows of about {cfg.frames / cfg.windows:.0f} "
            f"frames, each seen from its own pose")
    out.mkdir(parents=True, exist_ok=True)  # after every input is read: bad input leaves no run folder
    remove_stale_parts(out)  # a run killed while writing a checkpoint leaves its temporary behind
    ck_path = out / CHECKPOINT
    batch = Batch(tg, device)
    focal = ds.camera(H, W)  # a float (square pixels, centred) or (fl_x, fl_y, cx, cy)
    field = make_field(cfg, W, space).to(device)
    opt = make_optimizer(field, cfg)
    schedule = grid_schedule(cfg, W)
    legacy_windows = count_windows(ds, method, H, W, cfg.frames, method.windows)  # runs from before --windows
    mined = ErrorRays(batch.values.shape[0], H, W, cfg.error_rays, device) if cfg.error_rays > 0 else None
    field, opt, start, train_s, space = _resume(ck_path, cfg, (ds.frames, legacy_windows), device, field, opt, space,
                                                log, mined)
    write_json_atomic(out / "config.json", {**cfg.to_json(), "device_used": str(device), "height": H, "width": W,
                                            "holdout": ds.holdout, "heldout": ds.heldout, "grid_schedule": schedule,
                                            "intensity": ds.intensity})
    if start >= cfg.iters:
        log(f"{out}: already trained ({start} iterations)")
        return ck_path
    _loop(cfg, method, field, opt, batch, ds.intensity, (H, W, focal, ds.background, space), schedule, start,
          train_s, out, progress, stop_at or cfg.iters, mined, coarse)
    return ck_path


def _resolution(ds, res: int) -> tuple[int, int]:
    if not res or res == ds.width:
        return ds.height, ds.width
    if res < 8 or ds.width % res or ds.height % (ds.width // res):
        raise InputError(f"--resolution {res}: the dataset's {ds.width} x {ds.height} must shrink to width {res} "
                         "by one integer factor that divides both sides")
    f = ds.width // res
    return ds.height // f, res


def _resume(ck_path: Path, cfg: TrainConfig, legacy: tuple[int, int], device, field, opt, space, log, mined=None):
    """(field, optimizer, start iteration, training seconds, space): from the checkpoint if there is
    one (its field keeps the space it was made in: one from before NDC existed stays in the world cube).
    ``mined`` (``--error-rays``) takes the checkpoint's error map."""
    if not ck_path.is_file():
        return field, opt, 0, 0.0, space
    ck = load_checkpoint(ck_path, device)
    _check_resume(ck, cfg, ck_path, legacy)
    field = field_from_checkpoint(ck, device)
    opt = make_optimizer(field, cfg)
    opt.load_state_dict(ck["optimizer"])
    if mined is not None:
        mined.load_state_dict(ck["error_rays"])
    log(f"resuming from {ck_path} at iteration {int(ck['iteration'])}")
    return field, opt, int(ck["iteration"]), float(ck["train_seconds"]), checkpoint_space(ck)


def _checkpoint_config(out: Path) -> dict | None:
    """The settings recorded with the checkpoint in ``out`` (its ``config.json``), None without one: a run
    resumed without ``--windows`` or ``--srgb-weight`` keeps what it was made with (:func:`train`), whatever
    the defaults are now."""
    if not (out / CHECKPOINT).is_file() or not (out / "config.json").is_file():
        return None
    try:
        made = json.loads((out / "config.json").read_text())
    except (OSError, ValueError):
        return None
    return made if isinstance(made, dict) else None


def _positive_int(v) -> int | None:
    return int(v) if isinstance(v, int) and v > 0 else None


def _keep(out: Path, kept, now, name, log):
    """A resumed run's value of a setting it was not given: ``kept``, its checkpoint's (None: none recorded, then
    ``now``), said in one line where it differs from ``now``, the value a new run would take; ``name`` words a
    value."""
    if kept is None or kept == now:
        return now
    log(f"{out}: resuming with its {name(kept)} (a new run would take {now:g})")
    return kept


def _frames(ds, frames: int | None) -> int:
    """``--frames w``: 1 <= w <= the dataset's frames; None = all of them."""
    if frames is None:
        return ds.frames
    if not 1 <= frames <= ds.frames:
        raise InputError(f"--frames {frames}: must be between 1 and the dataset's {ds.frames} frames per stream")
    return int(frames)


def _loop(cfg, method, field, opt, batch, intensity, cam, schedule, start, train_s, out, progress, stop_at,
          mined=None, coarse=None):
    """``coarse`` (``--coarse-to-fine``): ((Batch, height, width, camera), first full-size iteration): the
    downsampled images the iterations before it draw their rays from; error rays start with the full size."""
    H, W, focal, background, space = cam
    fine = (batch, H, W, focal)
    ck_path = out / CHECKPOINT
    extra = {"height": H, "width": W, "focal_px": focal, "intensity": intensity, "background": background}
    if space is not None:  # no key: world coordinates (as every checkpoint from before NDC)
        extra["space"] = space.to_json()
    last_save, save_s = time.perf_counter(), 0.0  # save_s: how long the last save took
    bar = tqdm(range(start, cfg.iters), initial=start, total=cfg.iters, desc=f"train {cfg.method}",
               disable=not progress, unit="it")
    guard = LossGuard(batch.device, ck_path)
    t0 = time.perf_counter()
    for it in bar:
        if it >= stop_at:
            break
        field, opt = _grow(field, opt, cfg, schedule, it)
        if it >= cfg.occupancy_after and it % cfg.occupancy_every == 0:
            field.update_occupancy(cfg.occupancy_threshold)
        gen = iteration_generator(cfg.seed, it)
        at_coarse = coarse is not None and it < coarse[1]
        batch, h, w, camera = coarse[0] if at_coarse else fine
        mining = None if at_coarse else mined
        img, pix, jitter, weights = batch.draw(cfg.batch_rays, gen, mining,
                                               (it, cfg.seed) if cfg.ray_order == "shuffled" else None)
        o, d = pixel_rays(batch.poses[img], pix, h, w, camera)
        if space is None:
            # the composite the sensor model sees
            x, _ = render_rays(field, o, d, jitter, background, stop=cfg.stop_transmittance)
        else:  # sampled uniformly in NDC from the near plane, composited as evaluation and rendering do
            (x, _), _ = render_ndc_rays(field, space, o, d, jitter, background, stop=cfg.stop_transmittance)
        loss, pred, obs = method_loss(method, x, img, pix, batch, intensity, weights, cfg.srgb_weight)
        if cfg.tv_weight > 0:
            tv = (field.tv_at_points(gen, cfg.tv_points) if cfg.tv_points and not field.sparse
                  else field.tv_loss(gen, luminance=cfg.tv_luminance))
            loss = loss + cfg.tv_weight * tv
        guard.note(loss, it, bar)
        if mining is not None:
            mining.note(img, pix, pred, obs)
            mining.step_done(it)
        for g, base in zip(opt.param_groups, (cfg.lr_grid, cfg.lr_mlp)):
            g["lr"] = base * learning_rate_factor(it, cfg.iters, cfg.lr_decay)
        opt.zero_grad(set_to_none=False)  # the grids' gradients stay allocated: model._CornerRead adds into them
        loss.backward()
        opt.step()
        if it % 10 == 0:
            guard.check(bar)
        if it % 10 == 0 and not bar.disable:  # (reading these values waits for a GPU: only when shown)
            mse = float((pred.detach().clamp(0, 1) - obs.clamp(0, 1)).square().mean())
            bar.set_postfix(loss=f"{loss.item():.4g}", psnr=f"{-10 * math.log10(max(mse, 1e-10)):.2f}",
                            grid=field.grid_size, occ=f"{float(field.occupancy.float().mean()):.3f}")
        now = time.perf_counter()
        done = it + 1
        # by time: every checkpoint_every_s, but at least 20 save-durations apart (saves <= ~5 % of the time)
        if done in (cfg.iters, stop_at) or done % cfg.checkpoint_every == 0 or \
                now - last_save > max(cfg.checkpoint_every_s, 20 * save_s):
            guard.check(bar)
            _check_finite(field, it, ck_path, bar)
            save_checkpoint(ck_path, field, opt, cfg, done, train_s + now - t0,
                            extra if mined is None else {**extra, "error_rays": mined.state_dict()})
            last_save = time.perf_counter()
            save_s = last_save - now
    bar.close()


class LossGuard:
    """A NaN or infinite loss stops the run; the last good checkpoint is kept.

    On the CPU each step's loss is checked before its step. On a GPU reading the loss on the host
    would wait for the device every step (bench/bench_trainer_profile.py --count), so the check stays
    on the device: the first non-finite loss's iteration and value are kept there and read every 10
    iterations and before every checkpoint, so the run stops within 10 iterations of the bad one,
    names it, and never saves a field trained past it (``_check_finite`` also guards every save)."""

    def __init__(self, device: torch.device, ck_path: Path):
        self.deferred = device.type != "cpu"
        self.ck_path = ck_path
        self.first_it = self.first_loss = None

    def note(self, loss: torch.Tensor, it: int, bar) -> None:
        loss = loss.detach()
        if not self.deferred:
            if not torch.isfinite(loss):
                self._stop(float(loss), it, bar)
            return
        if self.first_it is None:
            self.first_it = torch.full((), -1, dtype=torch.long, device=loss.device)
            self.first_loss = torch.zeros((), dtype=loss.dtype, device=loss.device)
        new = ~torch.isfinite(loss) & (self.first_it < 0)
        self.first_it = torch.where(new, it, self.first_it)
        self.first_loss = torch.where(new, loss, self.first_loss)

    def check(self, bar) -> None:
        """(Deferred mode) stop if any loss noted so far was not finite."""
        if self.first_it is not None:
            it = int(self.first_it)
            if it >= 0:
                self._stop(float(self.first_loss), it, bar)

    def _stop(self, value: float, it: int, bar) -> None:
        bar.close()
        raise TrainError(f"loss became {'NaN' if math.isnan(value) else 'infinite'} at iteration {it}; stopped. The "
                         f"last good checkpoint {self.ck_path} is kept" +
                         ("" if self.ck_path.is_file() else " (none was written yet)"))


def _check_finite(field, it, ck_path, bar) -> None:
    """Never overwrite the last good checkpoint with a field that holds NaN or infinity."""
    if all(bool(torch.isfinite(p).all()) for p in field.parameters()):
        return
    bar.close()
    raise TrainError(f"the field became non-finite (NaN/inf) at iteration {it}; stopped. The last good "
                     f"checkpoint {ck_path} is kept" + ("" if ck_path.is_file() else " (none was written yet)"))


def _mlp_adam(opt) -> torch.optim.Optimizer | None:
    """The torch optimizer that holds the MLP's Adam state (keyed by parameter)."""
    return opt.mlp if isinstance(opt, LazyGridAdam) else opt


# The fitted box (GridField.fitted_box): the extent per axis of the grid points whose sample alpha
# exceeds BOX_ALPHA, less the BOX_TRIM fraction of them at either end (floaters), plus BOX_PAD voxels
# of the grid being cropped. Chosen on the procedural lego (docs/trainer.md, "The fitted box").
BOX_ALPHA, BOX_TRIM, BOX_PAD = 0.3, 1e-3, 2


def _grow(field, opt, cfg, schedule, it):
    """Upsample the grid where the schedule says (a new optimizer state for the grid); with
    ``fit_box``, from ``occupancy_after`` on, the grid is first cropped to the box the occupied
    space fills (DVGO's fitted bounding box), so that the finer grid spends its voxels there."""
    for at, size in schedule:
        if it == at and field.grid_size < size:
            if cfg.fit_box and it >= cfg.occupancy_after:
                field.crop(*field.fitted_box(BOX_ALPHA, BOX_TRIM, BOX_PAD))
            field.upsample(size)
            if it >= cfg.occupancy_after:
                field.update_occupancy(cfg.occupancy_threshold)
            old, opt = opt, make_optimizer(field, cfg)
            for p in field.mlp.parameters():  # the MLP keeps its Adam state; the grids' restarts
                if p in _mlp_adam(old).state:
                    _mlp_adam(opt).state[p] = _mlp_adam(old).state[p]
    return field, opt
