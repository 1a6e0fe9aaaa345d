"""bench/bench_trainer_scale.py's table: the ratio of the first two runs, which runs are converged (within
0.3 dB of three times their iterations), and a single run printed without a ratio (it used to fail)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
scale = pytest.importorskip("bench_trainer_scale")


def _row(res, iters, train_s, obj):
    return {"resolution": res, "iters": iters, "train_s": train_s, "eval_s": 1.0, "views": 2, "peak_rss_mb": 500.0,
            "checkpoint_mb": 10.0, "psnr": obj + 6, "psnr_object": obj, "load_after": 1.0}


def test_table_ratio_and_converged_runs(capsys):
    rows = [_row(100, 9000, 100.0, 29.4), _row(400, 9000, 250.0, 27.1), _row(400, 27000, 800.0, 26.6),
            _row(100, 27000, 300.0, 28.3), _row(400, 3000, 90.0, 25.0)]
    scale.table(rows)
    out = capsys.readouterr().out
    assert "training time ratio 400/100 (9000 / 9000 iterations): 2.50" in out
    # 400 at 3000 gains 2.1 dB by 9000: not converged; 400 at 9000 loses by 27000: converged
    assert "object PSNR at 9000 minus at 3000 iterations: +2.10 dB (converged within 0.3 dB: NO)" in out
    assert "400 x 400 converged at 9000 iterations (step 0.5) in 250 s: 2.50 times" in out
    assert "(target <= 3: met), 2.50 times the 100 x 100 run converged at 9000" in out
    assert scale.converged_runs(rows)[400]["iters"] == 9000


def test_table_of_one_run_has_no_ratio(capsys):
    scale.table([_row(100, 27000, 300.0, 28.3)])
    out = capsys.readouterr().out
    assert "28.30" in out and "ratio" not in out and "no 100 x 100 run is shown converged" in out


def _file(rows, dataset="D"):
    return {"dataset": dataset, "rows": rows}


def test_across_files_converged_runs_and_the_side_by_side_ratio(capsys):
    """Convergence over several files' rows (a run in two files counts once); the ratio of the converged runs
    only from a file holding both (times from different files were not made side by side)."""
    a = _file([_row(100, 3000, 50.0, 29.0), _row(400, 4500, 120.0, 26.3), _row(400, 13500, 360.0, 27.2)])
    b = _file([_row(100, 9000, 140.0, 29.4), _row(400, 9000, 230.0, 27.1)])
    c = _file([_row(100, 27000, 430.0, 28.3)])
    d = _file([_row(400, 27000, 900.0, 26.6)])
    scale.across([a, b, c], ["a", "b", "c"])
    out = capsys.readouterr().out
    assert "100 x 100: converged at 9000" in out and "no ratio of converged runs" in out  # 400 at 9000: no 27000
    scale.across([a, b, c, d], ["a", "b", "c", "d"])
    out = capsys.readouterr().out
    assert "400 x 400: converged at 9000" in out
    assert "side by side in b: 400 x 400 / 100 x 100 = 230.0 / 140.0 s = 1.64 (target <= 3: met)" in out
    scale.across([a, c, d], ["a", "c", "d"])  # the 9000-iteration runs nowhere: 100 x 100 not shown converged
    assert "no ratio of converged runs" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        scale.across([a, _file([], dataset="E")], ["a", "e"])


def test_runs_with_another_srgb_weight_are_not_each_others_3x_run(capsys):
    """A run's 3 x run has its sRGB weight too (``--srgb-weight``; rows without it: 0, off): a weighted run at
    three times the iterations says nothing of an unweighted one's convergence, and the lines name the weight."""
    plain, weighted = _row(400, 9000, 250.0, 27.7), {**_row(400, 27000, 800.0, 27.8), "srgb_weight": 400.0}
    assert scale.tripled([plain, weighted], plain) is None
    scale.table([plain, weighted])
    assert "no 400 x 400 run is shown converged" in capsys.readouterr().out
    rows = [{**plain, "srgb_weight": 400.0}, weighted]
    scale.table(rows)
    out = capsys.readouterr().out
    assert "400 x 400 (step 0.5, sRGB weight 400): object PSNR at 27000 minus at 9000 iterations: +0.10 dB" in out
    assert scale.converged_runs(rows)[400]["iters"] == 9000


@pytest.mark.parametrize("extra", [["--srgb-weight", "-1"], ["--srgb-weight", "nan"],
                                   ["--method", "oracle", "--srgb-weight", "400"]])
def test_srgb_weight_bad_input_is_one_line_before_any_run(tmp_path, monkeypatch, extra):
    """A negative or non-number weight, or one for a method without the likelihood: one line, nothing made."""
    monkeypatch.setattr(sys, "argv", ["bench_trainer_scale.py", str(tmp_path / "data"), "--out", str(tmp_path / "runs"),
                                      *extra])
    with pytest.raises(SystemExit) as e:
        scale.main()
    assert "--srgb-weight must be >= 0" in str(e.value) and "\n" not in str(e.value)
    assert not (tmp_path / "runs").exists()


def test_each_run_trains_at_the_trainers_default_weight_for_its_own_counts(tmp_path_factory, tmp_path):
    """Without ``--srgb-weight`` a run trains at the trainer's default for its data's counts, and its row records
    the weight it trained with (read from the run's config.json): 400 on the sphere at i64 (a white pixel counts 64
    spikes in 256 frames), 0 at i8 (8 spikes, fewer than 16). A weight given is the run's whatever the counts."""
    from test_trainer_cli import SIZE, sphere_dataset

    hi, lo = sphere_dataset(tmp_path_factory, intensity=64), sphere_dataset(tmp_path_factory, intensity=8)
    assert scale.child(str(hi), SIZE, 2, tmp_path / "hi", 1, False)["srgb_weight"] == 400.0
    assert scale.child(str(lo), SIZE, 2, tmp_path / "lo", 1, False)["srgb_weight"] == 0.0
    assert scale.child(str(lo), SIZE, 2, tmp_path / "given", 1, False, srgb_weight=400.0)["srgb_weight"] == 400.0


def test_the_child_is_given_a_weight_only_where_the_call_gave_one(tmp_path, monkeypatch):
    """The parent passes ``--srgb-weight`` to its runs only when it was given one (else each run's trainer decides
    by its counts), and the runs' folders say which."""
    calls = []

    def fake_run(cmd, **kw):
        calls.append(cmd)
        return type("Done", (), {"returncode": 0, "stderr": "",
                                 "stdout": json.dumps(_row(int(cmd[cmd.index("--child") + 1]), 3000, 1.0, 27.0))})()

    monkeypatch.setattr(scale.subprocess, "run", fake_run)
    for extra in ([], ["--srgb-weight", "0"]):
        monkeypatch.setattr(sys, "argv", ["bench_trainer_scale.py", str(tmp_path / "data"), "--out",
                                          str(tmp_path / "runs"), "--runs", "100:3000", *extra])
        scale.main()
    plain, zero = calls
    assert "--srgb-weight" not in plain and zero[zero.index("--srgb-weight") + 1] == "0.0"
    assert plain[plain.index("--out") + 1].endswith("run100_3000_step0.5_mined0")
    assert zero[zero.index("--out") + 1].endswith("run100_3000_step0.5_mined0_srgbw0")


def test_a_tables_header_names_each_runs_weight_where_they_differ():
    """One weight for all runs: said once (nothing where it is 0, off); runs at different weights: each run's."""
    a, b = _row(100, 3000, 100.0, 29.0), _row(400, 9000, 250.0, 27.0)
    assert scale._weights([a, b]) == ""
    assert scale._weights([{**a, "srgb_weight": 400.0}, {**b, "srgb_weight": 400.0}]) == " with --srgb-weight 400"
    assert scale._weights([{**a, "srgb_weight": 400.0}, b]) == " with --srgb-weight 400 (100:3000), 0 (400:9000)"
