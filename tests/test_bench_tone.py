"""bench/bench_tone.py: the tone of evaluated runs side by side, from their metrics.json; its record file
and its table again; a run without a tone is one line and exit 2."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
tone_bench = pytest.importorskip("bench_tone")
from spikenerf.metrics import Tone  # noqa: E402


def _run(root: Path, name: str, lift: float) -> Path:
    """A run folder whose metrics.json holds the tone of a dark square rendered ``lift`` too bright."""
    truth = np.full((100, 100), 0.5)
    truth[30:70, 30:70] = 0.005
    t = Tone()
    t.add(truth + np.where(truth < 0.01, lift, 0.0), truth, np.ones_like(truth))
    run = root / name
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"method": "spikelik", "resolution": [100, 100], "iterations": 10,
                                                  "views": 1, "tone": t.summary()}))
    (run / "config.json").write_text(json.dumps({"dataset": "/data/scene"}))
    return run


def test_the_table_shows_each_runs_lift_and_the_record_reprints_it(tmp_path, capsys):
    a, b = _run(tmp_path, "a", 0.0), _run(tmp_path, "b", 0.01)
    record = tmp_path / "tone.json"
    assert tone_bench.main([str(a), str(b), "--json", str(record), "--plot", str(tmp_path / "tone.png")]) == 0
    out = capsys.readouterr().out
    dark = next(line for line in out.splitlines() if line.startswith("| 0 to 0.01 |"))
    cells = [c.strip() for c in dark.strip("|").split("|")]
    # run a: 1600 pixels, no bias; run b: +0.01 over all and flat pixels: 0.005 -> 0.015 is +17.2 8-bit steps
    # (sRGB 0.061 -> 0.128)
    assert cells[1:6] == ["1600", "+0.0000", "1296", "+0.0000", "+0.0"]
    assert cells[6:11] == ["1600", "+0.0100", "1296", "+0.0100", "+17.2"]
    assert (tmp_path / "tone.png").stat().st_size > 0
    assert tone_bench.main(["--table", str(record)]) == 0
    assert capsys.readouterr().out == out


def test_a_run_without_a_tone_is_one_line(tmp_path, capsys):
    run = _run(tmp_path, "old", 0.0)
    m = json.loads((run / "metrics.json").read_text())
    del m["tone"]
    (run / "metrics.json").write_text(json.dumps(m))
    assert tone_bench.main([str(run), "--json", str(tmp_path / "t.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "spikenerf eval" in err and not (tmp_path / "t.json").exists()
    assert tone_bench.main([str(tmp_path / "missing")]) == 2
    assert "no metrics.json" in capsys.readouterr().err
