"""Build ``assets/bit_camera_model.json`` and ``assets/bit_camera_maps.npz`` from the measured
BIT camera calibration (shared/data/real/bit_camera_calibration_250x400.npz).

    python -m spikegen.assets_build ../shared/data/real/bit_camera_calibration_250x400.npz assets/

``lux_to_rate`` (spikes per frame per lux at nominal response) comes from the interval map at
335 lux: the firing probability is ``p = 1 / (D + 1)`` and ``p = R (335 + L_d) lux_to_rate``.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from .fpn import fit_map_model
from .spikeio import atomic_path, write_json_atomic

CAL_LUX = 335.0


def build(calibration, out_dir) -> dict:
    with np.load(calibration) as z:
        nl, nd, d_light = (z[k].astype(np.float64) for k in ("Nl", "Nd", "D_light"))
    resp = nl / np.median(nl)  # Nl is relative to pixel (0, 0): normalise to median 1
    p = 1.0 / (d_light + 1.0)  # D_light stores intervals D = 1/p - 1
    lux_to_rate = float(np.median(p / (resp * (CAL_LUX + nd))))
    model = fit_map_model(resp, nd)
    model["lux_to_rate"] = lux_to_rate
    model["reference_pixel_response_vs_median"] = float(nl[0, 0] / np.median(nl))
    out = Path(out_dir)
    write_json_atomic(out / "bit_camera_model.json", model)
    with atomic_path(out / "bit_camera_maps.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, responsivity=resp.astype(np.float32), dark_lux=nd.astype(np.float32))
    return model


if __name__ == "__main__":
    m = build(sys.argv[1], sys.argv[2])
    print(json.dumps({k: v for k, v in m.items() if not isinstance(v, list)}, indent=1))
