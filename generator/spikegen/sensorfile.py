"""A sensor on disk: ``PREFIX.json`` (parameters, statistical map model) + ``PREFIX.npz`` (maps).

``PREFIX.json``::

    {"format": "spikegen-sensor/1",
     "parameters": {"name": ..., "kind": "if", "electrons": 0, "reset": "subtract", ...},
     "maps": "PREFIX.npz",            # relative to the JSON's folder; null if R = 1 and d = 0
     "map_model": {...} or null,       # spikegen.fpn statistics, to draw maps of other sizes
     "notes": {...}}

``PREFIX.npz``: float32 ``[H, W]`` maps ``responsivity`` (R, median 1) and ``dark_rate``
(d, spikes per frame at nominal response).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .errors import InputError
from .sensor import SCALAR_FIELDS, Sensor
from .spikeio import atomic_path, write_json_atomic

FORMAT = "spikegen-sensor/1"


def _prefix(prefix) -> Path:
    p = Path(prefix)
    return p.with_suffix("") if p.suffix in (".json", ".npz") else p


def save_sensor(sensor: Sensor, prefix) -> tuple[Path, Path | None]:
    """Write ``PREFIX.json`` and (if the sensor has maps) ``PREFIX.npz``; returns both paths."""
    base = _prefix(prefix)
    json_path = base.parent / (base.name + ".json")
    npz_path = None
    maps = {k: np.asarray(v, dtype=np.float32) for k, v in
            (("responsivity", sensor.responsivity), ("dark_rate", sensor.dark_rate)) if v is not None}
    if maps:
        npz_path = base.parent / (base.name + ".npz")
        with atomic_path(npz_path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **maps)
    doc = {"format": FORMAT, "parameters": sensor.parameters(),
           "maps": npz_path.name if npz_path else None, "map_model": sensor.map_model, "notes": sensor.notes}
    write_json_atomic(json_path, doc)
    return json_path, npz_path


def load_sensor(path) -> Sensor:
    """Read a sensor JSON (and its maps). Raises InputError with one line on any problem."""
    path = Path(path)
    if path.suffix != ".json":
        path = path.parent / (path.name + ".json")
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such sensor file") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable sensor JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("parameters"), dict):
        raise InputError(f"{path}: not a spikegen sensor file (expected \"format\": \"{FORMAT}\")")
    params = {k: v for k, v in doc["parameters"].items() if k in SCALAR_FIELDS}
    maps = {}
    if doc.get("maps"):
        npz = path.parent / doc["maps"]
        try:
            with np.load(npz, allow_pickle=False) as z:
                maps = {k: np.array(z[k], dtype=np.float32) for k in ("responsivity", "dark_rate") if k in z.files}
        except (OSError, ValueError) as exc:
            raise InputError(f"{npz}: cannot read the sensor maps named by {path.name} ({exc})") from None
    try:
        return Sensor(**params, **maps, map_model=doc.get("map_model"), notes=doc.get("notes") or {})
    except (TypeError, ValueError, InputError) as exc:
        raise InputError(f"{path}: bad sensor parameters ({exc})") from None
