"""Named sensors (sensor-model.md, Presets) and how a ``--sensor`` argument becomes a Sensor.

- ``ideal``: R = 1, d = 0, no shot noise.
- ``paper``: R and d of the measured BIT camera (``assets/bit_camera_maps.npz``, R normalised to
  median 1, d = L_d * lux_to_rate). At the camera's own size (250 x 400) the measured maps are
  used as they are; at any other size maps are drawn from their statistics
  (``assets/bit_camera_model.json``, see :mod:`spikegen.fpn`), never resized.
- ``rsir``: the paper's reference generator (Poisson gray level + uniform interval noise each
  frame) with the same maps.
- ``calibrated``: ``assets/calibrated.json``, fitted to measured recordings by the fidelity tools.
"""
from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from .errors import InputError
from .sensor import Sensor

PRESETS = ("ideal", "paper", "rsir", "calibrated")


def asset_path(name: str) -> Path:
    return Path(str(resources.files("spikegen.assets").joinpath(name)))


@lru_cache(maxsize=1)
def bit_camera() -> tuple[dict, np.ndarray, np.ndarray]:
    """(map model with lux_to_rate, measured R [250, 400] median 1, measured d [250, 400])."""
    model = json.loads(asset_path("bit_camera_model.json").read_text())
    with np.load(asset_path("bit_camera_maps.npz")) as z:
        resp = z["responsivity"].astype(np.float32)
        dark = (z["dark_lux"] * model["lux_to_rate"]).astype(np.float32)
    return model, resp, dark


def paper_sensor(height: int, width: int, seed: int = 0, kind: str = "if", name: str = "paper") -> Sensor:
    model, resp, dark = bit_camera()
    base = Sensor(name=name, kind=kind, lux_to_rate=model["lux_to_rate"], camera_seed=int(seed), map_model=model,
                  notes={"maps": "BIT camera calibration (shared/data/real), see spikegen.fpn"})
    if (height, width) == resp.shape:
        return base.replace(responsivity=resp, dark_rate=dark)
    return base.sized(height, width)


def get_sensor(spec: str, height: int, width: int, seed: int = 0) -> Sensor:
    """A ``--sensor`` value (preset name or path to a sensor JSON) as a Sensor of size H x W."""
    spec = str(spec)
    if spec == "ideal":
        return Sensor(name="ideal")
    if spec == "paper":
        return paper_sensor(height, width, seed)
    if spec == "rsir":
        return paper_sensor(height, width, seed, kind="rsir", name="rsir")
    if spec == "calibrated":
        path = asset_path("calibrated.json")
        if not path.is_file():
            raise InputError("sensor 'calibrated' is not fitted in this install (assets/calibrated.json missing)")
        return _load(path, height, width, seed)
    p = Path(spec)
    if p.suffix == ".json" or p.exists():
        return _load(p, height, width, seed)
    raise InputError(f"unknown sensor {spec!r}: expected one of {', '.join(PRESETS)} or a sensor .json file")


def sensor_problem(spec: str) -> str | None:
    """Why ``spec`` names no sensor (``None`` if it names a preset or an existing sensor file);
    cheap: no maps are loaded."""
    spec = str(spec)
    if spec in PRESETS or Path(spec).is_file():
        return None
    if spec.endswith(".json"):
        return f"{spec}: no such sensor file"
    return f"unknown sensor {spec!r}: expected one of {', '.join(PRESETS)} or a sensor .json file"


def _load(path: Path, height: int, width: int, seed: int) -> Sensor:
    from .sensorfile import load_sensor

    sensor = load_sensor(path)
    if sensor.map_model is not None and sensor.shape not in (None, (height, width)):
        sensor = sensor.replace(responsivity=None, dark_rate=None, camera_seed=int(seed))
    return sensor.sized(height, width)
