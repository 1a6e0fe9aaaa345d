"""The benchmark protocol (bench/PROTOCOL.md): every run appended to one results file.

    python bench/bench_protocol.py --resolution 100 --sensors rsir --intensities 64 \
        --methods spikelik,spikenerf-paper,tfp32 --seeds 0,1,2
    python bench/bench_protocol.py --resolution 400 --device cuda \
        --results bench/results/protocol_gpu.jsonl                         # the paper's scale, on a GPU
    python bench/make_protocol.py                                          # PROTOCOL.md from the results

Per data set, sensor and intensity: ``spikegen convert`` (the real lego: its 100 train views are
trained on, its 100 ``val`` views, never seen in training, are the held-out views; a procedural
scene: ``spikegen render`` with the moving camera, its test split held out), then for every method
and seed ``spikenerf train`` and ``spikenerf eval``. Each finished run becomes one line of
``bench/results/protocol.jsonl``: what it was (data, sensor, intensity, method, what the method knows
of the sensor, resolution, seed, iterations, frames, rays a step (rows without it: the default
2048), the sRGB weight of ``--srgb-weight`` (the likelihood methods' rows; rows without it: 0, off: every run
before 2026-11-29 that did not set it), the order rays are drawn in (``--ray-order``; rows without it: ``uniform``,
every run before 2026-12-02), device), what it cost (train seconds, wall
seconds, the load average) and every metric (means and per view). A run already in the file is
skipped, so a long table is completed over several sessions; work folders live in ``--out``, and a
run interrupted there resumes from its checkpoint (its row says ``resumed_at``: the iteration it
resumed from; its wall_seconds are this session's only; train_seconds add up over sessions).
``--jobs N`` trains N runs at once (a GPU is busy about a third of a training step, the rest is the
host's: docs/trainer.md, so several runs can use one; 5 at once on an H200 gave about 2.1 times the
training throughput of one at a time: docs/trainer.md "fourth lease"); their rows say ``jobs``. ``--start-within S``:
no run starts after S seconds (for a machine lent for a fixed time). ``--calibrated`` adds, for every
method that uses the sensor's maps (or those of ``--calibrated-methods``), a run with the
maps of ``spikegen calibrate`` on simulated dark and flat recordings of the same camera (what a user of a
real camera has) instead of the dataset's true maps, fitted for the camera's own response (``--kind``: the
linear Eqs. S2-S6 for the integrate-and-fire sensors, the rsir fit for ``rsir``; rows say which in
``calibration_fit``, and rows without it were made with Eqs. S2-S6). ``--plan`` keeps, of the runs asked
for, those of the protocol's plan (bench/make_protocol.py ``PLAN``: what its "Still missing" counts), its
calibrated-maps runs included; with ``--ray-order shuffled``, the plan drawn in that order (what its "The plan
drawn in the shuffled order" counts: the runs the default's change waits for). No setting is chosen here: every
method runs with the trainer's defaults, except where a call names one (``--iters``, ``--frames``, ``--batch-rays``,
``--srgb-weight``, ``--ray-order``), which its rows state and the tables show in their own rows. ``oracle`` (not a
spike method; it knows the ground-truth images of the train views) is the same field fitted to those images: what
the field can represent.
"""
from __future__ import annotations

import argparse
import datetime
import functools
import itertools
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from spikegen.sensor import KINDS
from spikenerf.config import RAY_ORDERS, TrainConfig, default_iters
from spikenerf.methods import METHODS as TRAINER_METHODS
from spikenerf.methods import default_srgb_weight, white_count

REPO = Path(__file__).resolve().parents[1]
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_lego_400"
RESULTS = REPO / "bench" / "results" / "protocol.jsonl"
METHODS = ["spikelik", "spikenerf-paper", "spikenerf", "spikenerf-noR", "tfp32", "tfp256", "tfi", "oracle"]
# The trainer's field, recorded in every row: rows made with another field are not the same run (rows
# from before this key existed were made with the grid over the fixed cube [-1.5, 1.5]^3).
FIELD = "grid, fitted box"
OLD_FIELD = "grid, fixed cube"
# What each method knows of the camera's fixed pattern: the dataset's own (true) R and dark current,
# or nothing (it reconstructs images from the spikes, or assumes R = 1).
KNOWLEDGE = {"spikelik": "true maps", "spikenerf-paper": "true maps", "spikenerf": "true maps",
             "spikenerf-noR": "none", "tfp32": "none", "tfp256": "none", "tfi": "none",
             "oracle": "ground-truth images", "spikelik-count": "true maps"}
# Methods outside the plan that a call may still name: spikelik-count, the default before 2026-11-28
# (spikelik reading the counts alone; on the rsir sensor the same run as spikelik). The rows made on the
# integrate-and-fire sensors (paper, calibrated) as "spikelik" before then were relabelled to it.
EXTRA_METHODS = ["spikelik-count"]
TABLE_ORDER = METHODS[:1] + EXTRA_METHODS + METHODS[1:]  # the order of the methods in the tables
# The `calibrated` preset is refitted from time to time: every row records its temporal noise
# (sensor_model), and rows made with another preset are not the same runs. Rows from before this key
# were made with the preset of commits dfecb33 to 76ab7ef: shot noise of N_e = 1.383e4, no jitter.
LEGACY_CALIBRATED = {"electrons": 13829.406571440471, "threshold_jitter": 0.0}
KEY = ("data", "sensor", "intensity", "method", "knowledge", "resolution", "seed", "iterations", "frames", "field",
       "batch_rays", "calibration_fit", "srgb_weight", "ray_order")
# rays a training step (spikenerf train --batch-rays): rows without the key were made at the trainer's default
DEFAULT_RAYS = TrainConfig.__dataclass_fields__["batch_rays"].default
# each ray's display weight in the likelihood (spikenerf train --srgb-weight; 0 = off): rows without the key were
# made with it off (the trainer's default until 2026-11-29; its default now: spikenerf.methods.default_srgb_weight)
UNWEIGHTED = 0.0
# the order a run draws its rays in (spikenerf train --ray-order): rows without the key were made with the uniform
# draw, the trainer's only one before 2026-12-02 (and its default since)
UNIFORM = "uniform"
STREAM_FRAMES = 256  # the frames of every protocol dataset's streams (spikegen render's and convert's default)
# the methods that take --srgb-weight: those whose loss is the counts' likelihood (the trainer refuses it elsewhere)
SRGB_METHODS = tuple(name for name, m in TRAINER_METHODS.items() if m.loss == "nll")
CAL_INTENSITY, CAL_FRAMES = 64.0, 2000  # the simulated calibration recordings: a dark and two flats
CAL_FLATS_X = (0.25, 0.75)  # flat radiances; their "lux" is the nominal rate X * I / 256 (spikes per frame)


def _run(cmd: list[str]) -> str:
    print("$", " ".join(cmd), flush=True)
    res = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if res.returncode:
        last = (res.stderr.strip().splitlines() or ["?"])[-1]
        sys.exit(f"failed ({res.returncode}): {' '.join(cmd)}\n{last}")
    return res.stdout


def dataset(data: str, sensor: str, intensity: int, args) -> Path:
    """The spike dataset of one cell (made once, reused by every method and seed)."""
    root = args.out / f"data_{data}_{sensor}_{args.resolution}"
    if data == "lego":
        folder = root / f"{LEGO.name}_i{intensity}"
        if not (folder / "manifest.json").is_file():
            _run(["spikegen", "convert", str(LEGO), "--intensity", str(intensity), "--out", str(root),
                  "--sensor", sensor, "--resolution", str(args.resolution), "--workers", str(args.workers)])
        return folder
    folder = root / f"{data}_i{intensity}"
    if not (folder / "manifest.json").is_file():
        _run(["spikegen", "render", "--scene", data, "--intensity", str(intensity), "--out", str(root),
              "--sensor", sensor, "--resolution", str(args.resolution), "--views", args.scene_views,
              "--workers", str(args.workers)])
    return folder


@functools.lru_cache(maxsize=None)
def sensor_kind(sensor: str) -> str:
    """The response of a preset's camera (``if`` or ``rsir``): what its calibration is fitted for (loaded
    once a sensor: cells() and make_protocol ask per run)."""
    from spikegen.presets import get_sensor

    return get_sensor(sensor, 8, 8, 0).kind


def calibration(sensor: str, args, fit: str = "if") -> Path:
    """``spikegen calibrate --kind FIT`` on simulated dark and flat recordings of the dataset's camera
    (the same maps as its conversion: seed 0): the maps a user of a real camera has, not the true ones.
    The recordings are the same whatever the fit (seeded), so one already made is not made again."""
    import numpy as np

    from spikegen.presets import get_sensor
    from spikegen.sensor import simulate
    from spikegen.spikeio import write_spikes

    prefix = args.out / (f"calibration_{sensor}_{args.resolution}" + ("" if fit == "if" else f"_{fit}fit"))
    if prefix.with_suffix(".json").is_file():
        return prefix.with_suffix(".json")
    res = args.resolution
    camera = None
    paths = {}
    for k, x in enumerate((0.0, *CAL_FLATS_X)):
        paths[x] = args.out / f"calibration_{sensor}_{res}_x{x:g}.npz"
        if paths[x].is_file():  # written atomically: a file there is a whole recording
            continue
        camera = camera or get_sensor(sensor, res, res, 0).sized(res, res)
        write_spikes(paths[x], simulate(np.full((1, res, res), x, np.float32), CAL_INTENSITY, camera,
                                        frames=CAL_FRAMES, seed=1000 + k))
    flats = [f"--flat={x * CAL_INTENSITY / 256:g}={paths[x]}" for x in CAL_FLATS_X]
    _run(["spikegen", "calibrate", "--dark", str(paths[0.0]), *flats, "--out", str(prefix), "--kind", fit])
    return prefix.with_suffix(".json")


def sensor_model(sensor: str) -> dict:
    """The preset's temporal noise as rows record it (``sensor_model``)."""
    from spikegen.presets import get_sensor

    s = get_sensor(sensor, 8, 8, 0)
    return {"electrons": float(s.electrons), "threshold_jitter": float(s.threshold_jitter)}


def sensor_name(row: dict) -> str:
    """The sensor of a row as the tables and the resume group it: ``calibrated`` with its temporal
    noise (LEGACY_CALIBRATED for rows that do not record it), any other preset by its name."""
    if row["sensor"] != "calibrated":
        return row["sensor"]
    m = row.get("sensor_model") or LEGACY_CALIBRATED
    jitter = f", jitter SD {m['threshold_jitter']:.2g}" if m["threshold_jitter"] else ""
    return f"calibrated (N_e {m['electrons']:.4g}{jitter})"


def calibration_fit(row: dict) -> str | None:
    """The response a row's calibrated maps were fitted for (rows from before the key: Eqs. S2-S6,
    ``if``); None for a row that does not use calibrated maps."""
    return row.get("calibration_fit", "if") if row["knowledge"] == "calibrated maps" else None


def row_key(row: dict) -> tuple:
    return tuple(row.get(k, OLD_FIELD) if k == "field" else sensor_name(row) if k == "sensor" else
                 row.get(k, DEFAULT_RAYS) if k == "batch_rays" else calibration_fit(row) if k == "calibration_fit"
                 else srgb_weight(row) if k == "srgb_weight" else ray_order(row) if k == "ray_order" else row[k]
                 for k in KEY)


def srgb_weight(row: dict) -> float:
    """The row's ``--srgb-weight`` (rows without the key: off, UNWEIGHTED)."""
    return float(row.get("srgb_weight", UNWEIGHTED))


def ray_order(row: dict) -> str:
    """The row's ``--ray-order`` (rows without the key: UNIFORM)."""
    return row.get("ray_order", UNIFORM)


def done_keys(results: Path = RESULTS) -> set:
    if not results.is_file():
        return set()
    return {row_key(json.loads(line)) for line in results.read_text().splitlines() if line.strip()}


def run_one(folder: Path, cell: dict, args) -> dict:
    """Train and evaluate one run; the results line."""
    # (the folder's name: the key's values; the rays a step and the calibration's fit only where not the default,
    # the sRGB weight only where not off, the ray order only where not uniform, so that the folders of runs from
    # before those keys are found again and resume)
    name = "_".join(str(cell[k]) for k in KEY if k not in ("batch_rays", "calibration_fit", "srgb_weight",
                                                           "ray_order"))
    name = name.replace(" ", "-").replace(",", "")
    rays, fit, weight, order = cell["batch_rays"], calibration_fit(cell), srgb_weight(cell), ray_order(cell)
    run = args.out / f"runs_{args.resolution}" / (name + ("" if rays == DEFAULT_RAYS else f"_rays{rays}")
                                                  + ("" if fit in (None, "if") else f"_{fit}fit")
                                                  + ("" if weight == UNWEIGHTED else f"_srgbw{weight:g}")
                                                  + ("" if order == UNIFORM else f"_{order}"))
    cmd = ["spikenerf", "train", str(folder), "--method", cell["method"], "--out", str(run), "--device",
           args.device, "--seed", str(cell["seed"]), "--quiet", "--iters", str(cell["iterations"])]
    if cell["frames"]:
        cmd += ["--frames", str(cell["frames"])]
    if rays != DEFAULT_RAYS:
        cmd += ["--batch-rays", str(rays)]
    if cell["method"] in SRGB_METHODS:  # always said: the trainer's default is not that of every row
        cmd += ["--srgb-weight", f"{weight:g}"]
    cmd += ["--ray-order", order]  # always said, likewise
    if cell["knowledge"] == "calibrated maps":
        cmd += ["--sensor-maps", str(calibration(cell["sensor"], args, fit))]
    resumed = _checkpoint_iteration(run)
    load0, t0 = os.getloadavg()[0], time.perf_counter()
    _run(cmd)
    _run(["spikenerf", "eval", str(run), "--device", args.device, "--quiet"])
    wall = time.perf_counter() - t0
    m = json.loads((run / "metrics.json").read_text())
    cfg = json.loads((run / "config.json").read_text())
    per_view = m.pop("per_view")
    return {**cell, "device": cfg["device_used"], **_gpu(cfg["device_used"]), "train_seconds": m["train_seconds"],
            "wall_seconds": round(wall, 1), "load_average": [round(load0, 2), round(os.getloadavg()[0], 2)],
            "views_from": m.get("views_from"), "metrics": {k: v for k, v in m.items() if _metric(k)},
            "per_view": [{k: v for k, v in r.items() if k == "view" or _metric(k)} for r in per_view],
            "commit": _commit(), "date": datetime.date.today().isoformat(),
            "windows": cfg.get("windows"),  # the resolved count windows (None: a run from before --windows)
            **({"resumed_at": resumed} if resumed is not None else {})}


def _checkpoint_iteration(run: Path) -> int | None:
    """The iteration of a checkpoint an interrupted session left in the run folder (``spikenerf train``
    resumes from it; the row's wall_seconds then covers only this session's part), or None."""
    ckpt = run / "checkpoint.pt"
    if not ckpt.is_file():
        return None
    import torch
    return int(torch.load(ckpt, map_location="cpu", weights_only=False)["iteration"])


def _gpu(device: str) -> dict:
    """The GPU a CUDA run used, as ``{"gpu": name}`` (empty for a CPU run)."""
    if not device.startswith("cuda"):
        return {}
    import torch
    return {"gpu": torch.cuda.get_device_name(torch.device(device))}


def _metric(key: str) -> bool:
    return key.split("_")[0] in ("psnr", "ssim", "lpips")


def _commit() -> str:
    res = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return res.stdout.strip() + ("+changes" if dirty else "")


@functools.lru_cache(maxsize=None)
def planned(resolution: int, data: str, sensor: str, intensity: int) -> frozenset:
    """The (method, knowledge) runs the protocol's plan (bench/make_protocol.py ``PLAN``, whose "Still
    missing" lists those not yet made) holds for one cell; empty where it plans none. Read once a cell
    (:func:`cells` asks for every method and seed)."""
    import make_protocol  # (it imports this module, so not at the top)
    return frozenset(pair for res, datas, sensors, intensities, pairs in make_protocol.PLAN
                     if res == resolution and data in datas and sensor in sensors and intensity in intensities
                     for pair in pairs)


def cells(args):
    """Every run asked for: each method with what it knows, and (``--calibrated``) the methods that use
    maps once more with calibrated maps instead of the true ones, right after their true-maps runs (a
    budget that stops the list part-way leaves the comparison of the two whole where it began)."""
    chosen = (args.calibrated_methods or args.methods) if args.calibrated or args.plan else []
    variants = [v for m in args.methods for v in [(m, KNOWLEDGE[m])] +
                ([(m, "calibrated maps")] if KNOWLEDGE[m] == "true maps" and m in chosen else [])]
    for data, sensor, i, (method, knows), seed in itertools.product(args.data, args.sensors, args.intensities,
                                                                    variants, args.seeds):
        if args.plan and (method, knows) not in planned(args.resolution, data, sensor, i):
            continue
        yield data, sensor, i, {"data": data, "sensor": sensor, "intensity": i, "method": method,
                                "knowledge": knows, "resolution": args.resolution, "seed": seed,
                                "iterations": args.iters or default_iters(args.resolution, args.resolution),
                                "frames": args.frames, "field": FIELD, "batch_rays": args.batch_rays,
                                "ray_order": args.ray_order,
                                **({"srgb_weight": _weight(args, method, i)} if method in SRGB_METHODS else {}),
                                **({"calibration_fit": args.calibration_kind or sensor_kind(sensor)}
                                   if knows == "calibrated maps" else {})}


def default_weight(method: str, intensity: float, frames: int, windows: int = 1) -> float:
    """The trainer's default sRGB weight for a protocol run that trains from the first ``frames`` frames (0: all,
    STREAM_FRAMES) in ``windows`` count windows: the protocol's datasets are made at the run's size (no pixels
    averaged), and its scenes train with one window (the lego's views are static; every procedural row says 1)."""
    return default_srgb_weight(method, white_count(intensity, frames or STREAM_FRAMES, windows))


def _weight(args, method: str, intensity: float) -> float:
    """The sRGB weight a likelihood method's run trains with: ``--srgb-weight``, else the trainer's default."""
    return default_weight(method, intensity, args.frames) if args.srgb_weight is None else args.srgb_weight


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=400)
    ap.add_argument("--data", default="lego", help="lego and/or procedural scenes (chair,ficus,...)")
    ap.add_argument("--scene-views", default="100,0,50", help="train,val,test views of a procedural scene")
    ap.add_argument("--intensities", default="16,32,64")
    ap.add_argument("--sensors", default="rsir,paper,calibrated")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--iters", type=int, default=0, help="0 = the trainer's default for the resolution "
                    "(spikenerf.config.default_iters); the number is stated in every row")
    ap.add_argument("--frames", type=int, default=0, help="train from the first w frames (0 = all)")
    ap.add_argument("--batch-rays", type=int, default=DEFAULT_RAYS, help="rays a training step (spikenerf train "
                    "--batch-rays); stated in every row")
    ap.add_argument("--srgb-weight", type=float, default=None, help="each ray's display weight in the likelihood, "
                    "at most this (spikenerf train --srgb-weight; the likelihood methods only; 0 = off; default: the "
                    "trainer's); stated in the likelihood methods' rows")
    ap.add_argument("--ray-order", choices=RAY_ORDERS, default=TrainConfig.ray_order, help="the order a run draws "
                    "its rays in (spikenerf train --ray-order; default: the trainer's); stated in every row")
    ap.add_argument("--calibrated", action="store_true", help="also run the methods that use the sensor's maps "
                    "with maps from spikegen calibrate on simulated dark and flat recordings of the same camera")
    ap.add_argument("--calibrated-methods", default="", help="with --calibrated or --plan: only these of the "
                    "methods run once more with calibrated maps (default: every method given that uses the maps; "
                    "the protocol's plan, bench/make_protocol.py PLAN, has spikelik alone)")
    ap.add_argument("--plan", action="store_true", help="only the runs of the protocol's plan "
                    "(bench/make_protocol.py PLAN) among those asked for: the plan's (method, knowledge) pairs, its "
                    "calibrated-maps runs included (no --calibrated needed), at the default iterations, frames, rays "
                    "and sRGB weight; with --ray-order shuffled the plan drawn in that order (make_protocol's \"The "
                    "plan drawn in the shuffled order\" counts what is left of it)")
    ap.add_argument("--calibration-kind", choices=KINDS, default=None, help="the response the "
                    "calibrated maps are fitted for (spikegen calibrate --kind; default: the camera's own)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--jobs", type=int, default=1, help="runs trained at once, each its own process (a GPU is busy "
                    "about a third of a training step: several runs can use one); rows made with more than one say so "
                    "(jobs), their seconds are those of a shared machine")
    ap.add_argument("--start-within", type=float, default=0.0, help="seconds from now after which no run starts "
                    "(those left are said and left for a later call; 0 = no limit): a run cut by a time budget "
                    "on a lent machine is lost with it")
    ap.add_argument("--workers", type=int, default=1, help="local processes that make a dataset (spikegen --workers; "
                    "every view carries its own seed, so the bytes do not depend on it)")
    ap.add_argument("--out", type=Path, default=REPO / "bench_out" / "protocol")
    ap.add_argument("--results", type=Path, default=RESULTS, help="the results file rows are appended to (GPU runs: "
                    "bench/results/protocol_gpu.jsonl)")
    args = ap.parse_args()
    args.data, args.sensors, args.methods = (v.split(",") for v in (args.data, args.sensors, args.methods))
    try:
        args.intensities, args.seeds = ([int(v) for v in s.split(",")] for s in (args.intensities, args.seeds))
    except ValueError:
        sys.exit("--intensities and --seeds take comma-separated whole numbers")
    args.calibrated_methods = [m for m in args.calibrated_methods.split(",") if m]
    unknown = [m for m in args.methods + args.calibrated_methods if m not in KNOWLEDGE]
    if unknown or ("lego" in args.data and not LEGO.is_dir()):
        sys.exit(f"unknown methods {unknown}" if unknown else f"{LEGO} not found: the real lego is needed")
    if args.calibrated_methods and not (args.calibrated or args.plan):
        sys.exit("--calibrated-methods needs --calibrated or --plan")
    if args.plan and (args.iters not in (0, default_iters(args.resolution, args.resolution)) or args.frames
                      or args.batch_rays != DEFAULT_RAYS or args.srgb_weight is not None):
        sys.exit("--plan: the plan's runs are at the default iterations, frames, rays a step and sRGB weight "
                 "(no --iters, --frames, --batch-rays or --srgb-weight; --ray-order makes the plan in that order)")
    if args.srgb_weight is not None and (args.srgb_weight < 0 or not math.isfinite(args.srgb_weight)):
        sys.exit(f"--srgb-weight must be a number >= 0 (0 = off), got {args.srgb_weight}")
    unweighted = [m for m in args.methods if m not in SRGB_METHODS]
    if args.srgb_weight and unweighted:
        sys.exit(f"--srgb-weight is for the likelihood methods ({', '.join(SRGB_METHODS)}), "
                 f"not {', '.join(unweighted)}")
    mapless = [m for m in args.calibrated_methods if KNOWLEDGE[m] != "true maps" or m not in args.methods]
    if mapless:
        sys.exit(f"--calibrated-methods: {', '.join(mapless)} not among the --methods that use the sensor's maps")
    if args.jobs < 1 or args.start_within < 0:
        sys.exit("--jobs must be at least 1 and --start-within at least 0")
    args.deadline = time.monotonic() + args.start_within if args.start_within else math.inf
    done = done_keys(args.results)
    models = {s: sensor_model(s) for s in args.sensors}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    todo, asked = [], 0
    for data, sensor, i, cell in cells(args):
        asked += 1
        cell["sensor_model"] = models[sensor]
        if row_key(cell) in done:
            continue
        todo.append((data, sensor, i, cell))
    if not asked:  # (only --plan can leave none)
        print("no runs to make: the plan holds none of those asked for")
    elif not todo:
        print(f"no runs to make: {asked} asked for{' (of the plan)' if args.plan else ''}, "
              f"all already in {args.results}")
    run_plan(todo, args)


def _record(row: dict, args) -> None:
    """Append a finished run's row to the results file and say what it scored; a row made with
    ``--jobs`` above 1 says so (``jobs``)."""
    if args.jobs > 1:
        row = {**row, "jobs": args.jobs}
    with args.results.open("a") as fh:
        fh.write(json.dumps(row) + "\n")
    options = (f" --srgb-weight {srgb_weight(row):g}" if row["method"] in SRGB_METHODS else "") + \
        ("" if ray_order(row) == UNIFORM else f" --ray-order {ray_order(row)}")
    print(f"  {row['data']} {row['sensor']} i{row['intensity']} {row['method']}{options} seed {row['seed']}: PSNR "
          f"{row['metrics']['psnr']:.2f} / object {row['metrics']['psnr_object']:.2f}, train "
          f"{row['train_seconds']:.0f} s", flush=True)


def run_plan(todo: list, args) -> None:
    """The runs, ``--jobs`` at once, each row appended by this process as its run finishes. A run's
    dataset (and calibration) is made by this process, one at a time, when the first run that needs it
    is about to start (while the runs already started go on). A run that fails stops new ones from
    starting; those under way finish and are recorded, then the failure's message ends the program."""
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

    folders = {}
    failure = None
    queue = list(todo)
    with ThreadPoolExecutor(args.jobs) as pool:
        running = set()
        while queue or running:
            if queue and time.monotonic() > args.deadline:
                print(f"--start-within passed: {len(queue)} run{'s' if len(queue) != 1 else ''} not started, "
                      "left for a later call", flush=True)
                queue = []
            while queue and failure is None and len(running) < args.jobs:
                data, sensor, i, cell = queue.pop(0)
                try:
                    if (data, sensor, i) not in folders:
                        folders[(data, sensor, i)] = dataset(data, sensor, i, args)
                    if cell["knowledge"] == "calibrated maps":
                        calibration(sensor, args, cell["calibration_fit"])
                except SystemExit as e:  # a dataset that could not be made: no run starts after it
                    failure = e
                    break
                running.add(pool.submit(run_one, folders[(data, sensor, i)], cell, args))
            if not running:
                break
            finished, running = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                try:
                    _record(fut.result(), args)
                except SystemExit as e:  # _run's one line
                    failure = failure or e
    if failure is not None:
        raise failure


if __name__ == "__main__":
    main()
