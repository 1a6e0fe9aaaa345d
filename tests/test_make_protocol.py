"""bench/make_protocol.py: PROTOCOL.md is what the script makes of the committed results, and its
targets table computes the margins the issue asks for."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"
sys.path.insert(0, str(BENCH))
make_protocol = pytest.importorskip("make_protocol")


def test_protocol_page_is_generated_from_the_results(tmp_path, monkeypatch):
    monkeypatch.setattr(make_protocol, "OUT", tmp_path / "PROTOCOL.md")
    make_protocol.main()
    assert (tmp_path / "PROTOCOL.md").read_text() == (BENCH / "PROTOCOL.md").read_text(), \
        "bench/PROTOCOL.md is stale: run python bench/make_protocol.py"


def _row(method, knowledge, obj, seed=0, intensity=64, iterations=3000):
    return {"resolution": 400, "data": "lego", "sensor": "rsir", "intensity": intensity, "method": method,
            "knowledge": knowledge, "seed": seed, "frames": 0, "iterations": iterations,
            "metrics": {"psnr_object": obj}}


def test_targets_margins_and_verdicts():
    rows = [_row("spikelik", "true maps", 25.0 + 0.1 * s, seed=s) for s in range(3)]   # mean 25.1
    rows += [_row("spikenerf-paper", "true maps", 22.0 + 0.1 * s, seed=s) for s in range(3)]  # 22.1
    rows += [_row("tfp32", "none", 20.0), _row("tfi", "none", 25.5)]
    rows += [_row("spikelik", "calibrated maps", 24.4)]
    rows += [_row("oracle", "ground-truth images", 26.1)]
    rows += [_row("spikelik", "true maps", 20.0, intensity=16)]
    rows += [_row("spikelik", "true maps", 40.0, iterations=9000)]  # another iteration count: its own line
    table = make_protocol.targets(rows)
    i64 = next(line for line in table if "| i64 |" in line and "3000 it" in line)
    cells = [c.strip() for c in i64.split("|")[1:-1]]
    assert cells[2] == "+3.00 (met)"                                   # 25.1 - 22.1, three seeds each
    assert cells[3].startswith("-0.40 (not met; 1 of 3 seeds) vs tfi")  # the best baseline is tfi
    assert "(2 of 5 baselines run)" in cells[3]
    assert cells[4] == "-0.70 (not met; 1 of 3 seeds)"                 # calibrated 24.4 vs true 25.1
    assert cells[5] == "+4.00"                                         # oracle 26.1 over the port 22.1
    i16 = next(line for line in table if "| i16 |" in line)
    assert [c.strip() for c in i16.split("|")[1:-1]][2:] == ["–", "–", "–", "–"]   # no port at i16: no ceiling
    rows += [_row("spikenerf-paper", "true maps", 21.0, intensity=16)]
    i16 = next(line for line in make_protocol.targets(rows) if "| i16 |" in line)
    assert [c.strip() for c in i16.split("|")[1:-1]][5] == "+5.10 (i64's oracle)"  # the oracle reads no spikes
    assert not any("| i32 |" in line for line in table)                # no default run: no line
    other = next(line for line in table if "9000 it" in line)         # not mixed into the 3000 means
    assert [c.strip() for c in other.split("|")[1:-1]][2:] == ["–", "–", "–", "–"]


def test_the_oracle_of_another_sensor_stands_in_where_a_sensor_has_none():
    """The oracle's datasets of one scene differ only in the spikes it never reads: a sensor without
    oracle runs takes those of its own other intensities first, then another sensor's at the same
    intensity, then at another; never those of another size or budget."""
    def row(sensor, method, obj, intensity=64, **kw):
        return dict(_row(method, "ground-truth images" if method == "oracle" else "true maps", obj,
                         intensity=intensity, **kw), sensor=sensor)

    def ceiling(rows, sensor, intensity):
        line = next(line for line in make_protocol.targets(rows) if f"lego, {sensor}," in line
                    and f"| i{intensity} |" in line and "3000 it" in line)
        return [c.strip() for c in line.split("|")[1:-1]][5]

    rows = [row(s, m, v, i) for s in ("paper", "rsir") for i in (16, 64)
            for m, v in (("spikelik", 25.0), ("spikenerf-paper", 22.0))]
    rows += [row("rsir", "oracle", 26.5, 64), row("rsir", "oracle", 27.5, 64, iterations=9000),
             dict(row("rsir", "oracle", 30.0, 16), resolution=100)]
    assert ceiling(rows, "rsir", 64) == "+4.50"
    assert ceiling(rows, "rsir", 16) == "+4.50 (i64's oracle)"
    assert ceiling(rows, "paper", 64) == "+4.50 (rsir i64's oracle)"   # not the 9000 or the 100 x 100 run
    assert ceiling(rows, "paper", 16) == "+4.50 (rsir i64's oracle)"
    rows += [row("rsir", "oracle", 25.5, 16)]
    assert ceiling(rows, "paper", 16) == "+3.50 (rsir i16's oracle)"    # the same intensity first
    rows += [row("paper", "oracle", 26.0, 64)]
    assert ceiling(rows, "paper", 16) == "+4.00 (i64's oracle)"         # then the same sensor first
    assert ceiling(rows, "paper", 64) == "+4.00"
    rows += [row("rsir", "spikenerf-paper", 24.0, 16)]                 # rsir i16: port 23.0 mean, oracle 25.5
    rows += [row("paper", "spikenerf-paper", 23.0, 16)]                # paper i16: port 22.5 mean, oracle 26.0
    text = make_protocol.targets(rows)[-1]
    assert "less than 3 dB above the port" in text and "lego, rsir, 400 x 400, 3000 it, i16" in text.split(".")[0]
    assert "lego, paper, 400 x 400, 3000 it, i16 (the default 1.00 dB below the oracle)" in text.split(". It")[1]


def test_sequence_table_sets_the_first_w_frames_beside_all_256():
    rows = [dict(_row("spikelik", "true maps", 24.0 + w / 64 + 0.2 * s, seed=s), frames=w)
            for w in (32, 64) for s in range(2)]                                   # 24.6, 25.1
    rows += [dict(_row("spikenerf-paper", "true maps", 23.0), frames=32)]
    rows += [_row("spikelik", "true maps", 26.0, seed=s) for s in range(3)]        # all 256 frames
    rows += [_row("spikenerf-paper", "true maps", 25.5), _row("tfi", "none", 20.0)]
    rows += [dict(_row("spikelik", "true maps", 30.0), frames=32, iterations=9000)]  # another budget
    rows += [dict(_row("spikelik", "calibrated maps", 10.0), frames=32)]            # not the method's own maps
    table = make_protocol.sequence_table(rows)
    assert table[0] == "### lego, rsir, 400 x 400, i64, 3000 iterations"
    assert table[2] == "| object PSNR | knows | w = 32 | w = 64 | w = 256 |"
    assert table[4] == "| spikelik | true maps | 24.60 ± 0.14 (2) | 25.10 ± 0.14 (2) | 26.00 ± 0.00 (3) |"
    assert table[5] == "| spikenerf-paper | true maps | 23.00 (1) | – | 25.50 (1) |"
    assert table[6] == "| default − port | | +1.60 | – | +0.50 |"
    assert not any(line.startswith("| tfi") for line in table)                      # no run from fewer frames
    assert "9000 iterations" in table[8] and "| spikelik | true maps | 30.00 (1) | – |" in table[12]
    assert make_protocol.sequence_table([_row("spikelik", "true maps", 26.0)]) == []


def test_sequence_table_names_the_earlier_default_by_its_label():
    """Runs made before the sRGB weight became the default (rows without it, labelled ``spikelik --srgb-weight
    0`` by load) stand in the sequence table with the method's own knowledge, and their margin over the port
    is said under their label, apart from the default's."""
    rows = [dict(_row("spikelik --srgb-weight 0", "true maps", 24.0), frames=32),
            _row("spikelik --srgb-weight 0", "true maps", 26.0),
            dict(_row("spikenerf-paper", "true maps", 23.0), frames=32), _row("spikenerf-paper", "true maps", 25.5),
            _row("spikelik", "true maps", 26.6)]  # the default, from all frames only
    table = make_protocol.sequence_table(rows)
    assert "| spikelik --srgb-weight 0 | true maps | 24.00 (1) | 26.00 (1) |" in table
    assert "| spikelik --srgb-weight 0 − port | | +1.00 | +0.50 |" in table
    assert not any(line.startswith("| default − port") for line in table)  # no default run from fewer frames


def test_a_margin_over_the_best_baseline_inside_the_seeds_noise_is_a_tie():
    rows = [_row("spikelik", "true maps", 25.0 + 0.1 * s, seed=s) for s in range(3)]       # 25.1, SD 0.1
    rows += [_row("spikenerf", "true maps", 25.05 + 0.1 * s, seed=s) for s in range(3)]     # 25.15, SD 0.1

    def cell(rows):
        line = next(line for line in make_protocol.targets(rows) if "| i64 |" in line)
        return [c.strip() for c in line.split("|")[1:-1]][3]

    band = 2 * np.sqrt(0.01 / 3 + 0.01 / 3)                                                  # 0.163
    assert cell(rows) == f"-0.05 (tie: within ±{band:.2f}) vs spikenerf (1 of 5 baselines run)"
    lower = [_row("tfi", "none", 24.0 + 0.1 * s, seed=s) for s in range(2)]                  # 24.05: beaten
    assert cell([r for r in rows if r["method"] != "spikenerf"] + lower).startswith("+1.05 (met; 2 of 3 seeds) vs tfi")
    one = [_row("spikenerf", "true maps", 25.09)]                                            # one seed: no band
    assert cell(rows[:3] + one).startswith("+0.01 (met; 1 of 3 seeds) vs spikenerf")
    assert make_protocol.tie_band([1.0], [1.0, 2.0]) is None


def test_missing_counts_only_runs_at_the_default_iteration_count():
    """At 400 x 400 the default is 9000 iterations: a run at 3000 does not fill its planned slot, one at 9000 does;
    a run from the first w frames does not either."""
    old = [_row("spikelik", "true maps", 25.0, seed=s) for s in range(3)]           # 3000 iterations
    new = [_row("spikelik", "true maps", 25.0, seed=s, iterations=9000) for s in range(2)]
    part = [dict(_row("spikelik", "true maps", 25.0, seed=2, iterations=9000), frames=64)]

    def left(rows):
        line = next(x for x in make_protocol.missing(rows) if "lego, rsir, 400 x 400" in x)
        assert "at 9000 iterations" in line
        return int(line.split(": ")[1].split(" of ")[0])

    assert left(old) == left([]) == 72
    assert left(old + new + part) == 70
    note = make_protocol.iterations_note(old + new)
    assert "2 runs at the default 9000" in note and "3 at 3000" in note


def test_missing_names_each_run_with_what_its_method_knows():
    """The plan holds every method with its own knowledge and, on the lego, the default with calibrated maps:
    a run with calibrated maps fills that slot only, and the line names what is left per method."""
    true = [_row("spikelik", "true maps", 25.0, seed=s, intensity=i, iterations=9000) for s in range(3)
            for i in (16, 32, 64)]
    cal = [_row("spikelik", "calibrated maps", 25.0, seed=0, intensity=64, iterations=9000)]
    tfi = [_row("tfi", "none", 20.0, seed=s, intensity=i, iterations=9000) for s in range(3) for i in (16, 32)]
    line = next(x for x in make_protocol.missing(true + cal + tfi) if "lego, rsir, 400 x 400" in x)
    assert line.split(": ")[1].startswith(f"{72 - 9 - 1 - 6} of 72 runs")
    named = line.split("not yet run: ")[1].split("; ")
    assert "spikelik with calibrated maps i16 (seeds 0, 1, 2), i32 (seeds 0, 1, 2), i64 (seeds 1, 2)" in named
    assert "tfi i64 (seeds 0, 1, 2)" in named
    assert not any(x.startswith("spikelik i") for x in named)  # the default on true maps: every run made
    only_cal = next(x for x in make_protocol.missing(cal) if "lego, rsir, 400 x 400" in x)
    assert ("spikelik i16 (seeds 0, 1, 2), i32 (seeds 0, 1, 2), i64 (seeds 0, 1, 2)"  # the true-maps slot: not filled
            in only_cal.split("not yet run: ")[1].split("; "))


def test_scenes_table_puts_the_procedural_scenes_side_by_side():
    """One line per method, one column per scene (mean over seeds, their number), the mean of the scene means
    only when every scene has the method; other iteration counts, partial sequences and the real lego stay out."""
    def row(data, method, knowledge, full, obj, seed=0, **kw):
        r = {"resolution": 100, "data": data, "sensor": "rsir", "intensity": 64, "method": method,
             "knowledge": knowledge, "seed": seed, "frames": 0, "iterations": 3000,
             "metrics": {"psnr": full, "psnr_object": obj}}
        return {**r, **kw}

    rows = [row("chair", "spikelik", "true maps", 30.0 + s, 25.0 + s, seed=s) for s in range(3)]  # 31 / 26 (3)
    rows += [row("mic", "spikelik", "true maps", 28.0, 24.0)]
    rows += [row("chair", "tfp32", "none", 20.0, 18.0)]                                       # no mic run
    rows += [row("chair", "spikelik", "true maps", 99.0, 99.0, iterations=9000),                # all left out
             row("chair", "spikelik", "true maps", 99.0, 99.0, frames=64),
             row("lego", "spikelik", "true maps", 99.0, 99.0)]
    table = make_protocol.scenes_table(rows)
    assert table[0] == "### rsir sensor, intensity 64, 100 x 100, 3000 iterations"
    assert table[2] == "| method | knows | chair | mic | mean of the scene means |"
    cells = lambda line: [c.strip() for c in line.split("|")[1:-1]]  # noqa: E731
    lik = next(cells(x) for x in table if x.startswith("| spikelik"))
    assert lik == ["spikelik", "true maps", "31.00 / 26.00 (3)", "28.00 / 24.00 (1)", "29.50 / 25.00"]
    tfp = next(cells(x) for x in table if x.startswith("| tfp32"))
    assert tfp == ["tfp32", "none", "20.00 / 18.00 (1)", "–", "–"]
    assert lik and not any("99.00" in x for x in table)
    gone = [x for x in make_protocol.missing(rows) if ", rsir, 100 x 100" in x and not x.startswith("- lego")]
    assert any(x.startswith("- chair") and "17 of 21 runs (i64, method x seed)" in x for x in gone)
    assert any(x.startswith("- ficus") and "21 of 21 runs" in x for x in gone)


def test_rows_of_different_calibrated_presets_are_different_runs():
    """A row records its preset's temporal noise; rows from before that key were made with N_e =
    1.383e4 and no jitter. The tables and the resume keep the two presets apart."""
    import bench_protocol

    old = {**_row("spikelik", "true maps", 25.0), "sensor": "calibrated", "field": bench_protocol.FIELD,
           "iterations": 9000}
    new = {**old, "sensor_model": bench_protocol.sensor_model("calibrated")}
    assert bench_protocol.sensor_name(old) == "calibrated (N_e 1.383e+04)"
    assert bench_protocol.sensor_name(new) != bench_protocol.sensor_name(old)
    assert "jitter SD" in bench_protocol.sensor_name(new)  # the preset now has a threshold jitter
    assert bench_protocol.row_key(new) != bench_protocol.row_key(old)
    rsir = {**old, "sensor": "rsir"}
    assert bench_protocol.sensor_name(rsir) == "rsir"


def test_gpu_rows_sit_beside_the_same_run_on_the_cpu():
    """A GPU row is matched to the CPU row of the same protocol key (its object PSNR difference shown), an
    unmatched one shows none, and a run with three times the iterations gives the convergence line."""
    import bench_protocol
    base = {**_row("spikelik", "true maps", 25.0, iterations=9000), "sensor": "rsir", "field": bench_protocol.FIELD,
            "train_seconds": 3000.0, "wall_seconds": 3300.0, "device": "cpu"}
    base["metrics"] = {"psnr": 30.0, "psnr_object": 25.0}
    cpu = [base]
    gpu = [{**base, "device": "cuda", "gpu": "NVIDIA H200", "train_seconds": 90.0, "wall_seconds": 120.0,
            "metrics": {"psnr": 30.1, "psnr_object": 25.04}},
           {**base, "device": "cuda", "gpu": "NVIDIA H200", "iterations": 27000, "train_seconds": 230.0,
            "wall_seconds": 260.0, "metrics": {"psnr": 31.0, "psnr_object": 26.0}}]
    lines = make_protocol.gpu_section(gpu, cpu)
    short = next(line for line in lines if "| 9000 |" in line)
    assert short.endswith("| 30.00 / 25.00, 3000 s | +0.040 |")
    long = next(line for line in lines if "| 27000 |" in line)
    assert long.endswith("| – | – |")
    assert any("largest GPU − CPU difference in object PSNR is 0.040 dB" in line for line in lines)
    conv = next(line for line in lines if "0.3 dB criterion" in line)
    assert "+0.96 dB" in conv and "not converged at 9000" in conv
    # a run resumed in a later call: its wall seconds are that call's part alone, and the line says so
    resumed = make_protocol.gpu_section([{**gpu[0], "wall_seconds": 85.0, "resumed_at": 8000}], cpu)
    assert any("| 85 (resumed at iteration 8000) |" in line for line in resumed)
    assert not any("resumed" in line for line in lines)


def test_gpu_section_pairs_only_runs_the_cpu_made(tmp_path, monkeypatch):
    """The page from the committed results: a GPU run that fills a table is not paired with itself (the
    GPU section's CPU column and its count of runs made on both read the CPU's results alone)."""
    import bench_protocol
    monkeypatch.setattr(make_protocol, "OUT", tmp_path / "PROTOCOL.md")
    make_protocol.main()
    text = (tmp_path / "PROTOCOL.md").read_text()
    cpu, gpu = (make_protocol.current(make_protocol.load(f)) for f in (make_protocol.RESULTS, make_protocol.GPU_RESULTS))
    both = len({bench_protocol.row_key(r) for r in cpu} & {bench_protocol.row_key(r) for r in gpu})
    assert (f"Runs made on both: {both};" in text) == (both > 0)


def test_rows_with_other_rays_a_step_are_other_runs():
    """A row records its rays a step (rows without it: the trainer's default); a run with another count
    is its own key, its own table line and target line, and fills no planned slot."""
    import bench_protocol
    assert bench_protocol.DEFAULT_RAYS == 2048
    base = {**_row("spikelik", "true maps", 25.0, iterations=9000), "field": bench_protocol.FIELD}
    wide = {**base, "batch_rays": 8192, "metrics": {"psnr_object": 30.0}}
    assert bench_protocol.row_key(base) == bench_protocol.row_key({**base, "batch_rays": 2048})
    assert bench_protocol.row_key(wide) != bench_protocol.row_key(base)
    lines = make_protocol.table([base, wide], "psnr_object", "method")
    assert any("| 9000 |" in x and "25.00" in x for x in lines)
    assert any("| 9000 (8192 rays) |" in x and "30.00" in x for x in lines)
    targets = make_protocol.targets([base, wide])
    assert sum("| i64 |" in x for x in targets) == 2 and any("9000 (8192 rays) it" in x for x in targets)

    def left(rows):
        line = next(x for x in make_protocol.missing(rows) if "lego, rsir, 400 x 400" in x)
        return int(line.split(": ")[1].split(" of ")[0])
    assert left([wide]) == left([]) == left([base]) + 1


def test_jobs_run_the_plan_at_once_and_record_every_run_once(tmp_path, monkeypatch):
    """``bench_protocol.py --jobs 2``: the runs not yet in the results file are trained two at a time,
    each finished run appended once with ``jobs``; a run that fails stops new ones from starting, the
    one under way is still recorded, and the program ends with the failure's line."""
    import threading
    import time

    import bench_protocol

    results = tmp_path / "rows.jsonl"
    already = {"data": "chair", "sensor": "rsir", "intensity": 64, "method": "tfp32", "knowledge": "none",
               "resolution": 100, "seed": 0, "iterations": 3000, "frames": 0, "field": bench_protocol.FIELD,
               "batch_rays": bench_protocol.DEFAULT_RAYS}
    results.write_text(json.dumps(already) + "\n")
    lock, live, most, fail_on = threading.Lock(), [0], [0], [None]

    def run_one(folder, cell, args):
        with lock:
            live[0] += 1
            most[0] = max(most[0], live[0])
        failing = (cell["method"], cell["seed"]) == fail_on[0]
        # the failing run ends at once, the others take a second: the failure is seen before its partner
        # finishes, so no new run may start (a partner ending first would rightly let the next one start)
        time.sleep(0.0 if failing else (1.0 if fail_on[0] else 0.2))
        with lock:
            live[0] -= 1
        if failing:
            raise SystemExit(f"failed (1): spikenerf train {folder}")
        return {**cell, "train_seconds": 1.0, "metrics": {"psnr": 30.0, "psnr_object": 25.0}}

    monkeypatch.setattr(bench_protocol, "run_one", run_one)
    monkeypatch.setattr(bench_protocol, "dataset", lambda data, sensor, i, args: tmp_path / f"{data}_i{i}")
    argv = ["bench_protocol.py", "--resolution", "100", "--data", "chair", "--sensors", "rsir", "--intensities", "64",
            "--methods", "tfp32,tfi", "--seeds", "0,1", "--jobs", "2", "--results", str(results), "--out", str(tmp_path)]
    monkeypatch.setattr(sys, "argv", argv)
    bench_protocol.main()
    rows = [json.loads(x) for x in results.read_text().splitlines()]
    assert sorted((r["method"], r["seed"]) for r in rows[1:]) == [("tfi", 0), ("tfi", 1), ("tfp32", 1)]
    assert all(r["jobs"] == 2 for r in rows[1:]) and most[0] == 2  # two at a time, never more
    bench_protocol.main()  # everything done: nothing more
    assert len(results.read_text().splitlines()) == 4

    results.write_text(json.dumps(already) + "\n")
    fail_on[0] = ("tfp32", 1)  # the second of the first pair fails: the first is recorded, no new run starts
    with pytest.raises(SystemExit, match="failed"):
        bench_protocol.main()
    rows = [json.loads(x) for x in results.read_text().splitlines()]
    assert [(r["method"], r["seed"]) for r in rows[1:]] == [("tfi", 0)]


def test_gpu_runs_at_the_default_budget_fill_the_tables_once():
    """A GPU run at the default budget (9000 iterations at 400 x 400, the default rays a step) that the
    CPU has not made stands in the tables; one the CPU made is tabled from the CPU; a GPU run at another
    budget (a convergence or rays-a-step experiment) stays in the GPU section alone."""
    extra = {"train_seconds": 100.0, "load_average": [1.0, 1.0], "views_from": "val", "commit": "abc"}

    def gpu(method, seed, **kw):
        return {**_row(method, "true maps", 26.0, seed=seed, iterations=9000), **extra, "device": "cuda", **kw}

    cpu = [{**_row("spikelik", "true maps", 25.0, seed=0, iterations=9000), **extra, "device": "cpu"}]
    twin, new = gpu("spikelik", 0), gpu("spikelik", 1)
    longer, wider = gpu("spikelik", 1, iterations=27000), gpu("spikelik", 1, batch_rays=8192)
    assert make_protocol.gpu_fills([twin, new, longer, wider], cpu) == [new]
    section = make_protocol.section(400, "lego", "rsir", cpu + [new])
    assert "device: cpu (1 runs), cuda (1 runs)" in section[2]
    assert any("Train seconds on cpu" in line and "Train seconds on cuda" in line for line in section)


@pytest.mark.parametrize("extra, message", [
    (["--calibrated-methods", "spikelik"], "--calibrated-methods needs --calibrated or --plan"),
    (["--plan", "--iters", "100"], "--plan: the plan's runs are at the default iterations"),
    (["--seeds", ""], "--intensities and --seeds take comma-separated whole numbers"),
    (["--intensities", "16,x"], "--intensities and --seeds take comma-separated whole numbers"),
    (["--plan", "--frames", "32"], "--plan: the plan's runs are at the default iterations"),
    (["--plan", "--batch-rays", "8192"], "--plan: the plan's runs are at the default iterations"),
    (["--calibrated", "--calibrated-methods", "tfp32"], "tfp32 not among the --methods that use the sensor's maps"),
    (["--calibrated", "--calibrated-methods", "spikenerf"], "spikenerf not among"),
    (["--calibrated", "--calibrated-methods", "nope"], "unknown methods ['nope']"),
    (["--plan", "--srgb-weight", "400"], "--plan: the plan's runs are at the default iterations"),
    (["--srgb-weight", "400"], "--srgb-weight is for the likelihood methods (spikelik, spikelik-count), not tfp32"),
    (["--methods", "spikelik", "--srgb-weight", "-1"], "--srgb-weight must be a number >= 0"),
    (["--methods", "spikelik", "--srgb-weight", "nan"], "--srgb-weight must be a number >= 0")])
def test_runner_bad_input(tmp_path, monkeypatch, extra, message):
    """--calibrated-methods without --calibrated or --plan, or naming a method that is not run with the
    sensor's maps; --plan off the default budget or sRGB weight; --srgb-weight for a method without the
    likelihood, or below 0; intensities or seeds that are not whole numbers: one line, before anything is made."""
    import bench_protocol
    monkeypatch.setattr(sys, "argv", ["bench_protocol.py", "--data", "chair", "--methods", "spikelik,tfp32",
                                      "--out", str(tmp_path / "out"), "--results", str(tmp_path / "r.jsonl"), *extra])
    with pytest.raises(SystemExit) as e:
        bench_protocol.main()
    assert message in str(e.value) and "\n" not in str(e.value)
    assert not any(tmp_path.iterdir())


def test_plan_asks_for_the_runs_still_missing_counts():
    """``--plan`` keeps, of the runs asked for, those of make_protocol's PLAN: with nothing made, as many
    as "Still missing" counts for every planned cell, the calibrated-maps runs included without
    --calibrated; none for a sensor or intensity outside the plan; the procedural scenes without them."""
    import argparse

    import bench_protocol
    sensors, intensities = ["rsir", "paper", "calibrated", "ideal"], [8, 16, 32, 64]

    def runs(res, data, **kw):
        args = argparse.Namespace(**{"data": [data], "sensors": sensors, "intensities": intensities,
                                     "methods": list(bench_protocol.METHODS), "seeds": [0, 1, 2], "calibrated": False,
                                     "calibrated_methods": [], "resolution": res, "iters": 0, "frames": 0,
                                     "batch_rays": 2048, "calibration_kind": None, "plan": True,
                                     "srgb_weight": None, "ray_order": "uniform", **kw})
        return [(c["sensor"], c["intensity"], c["method"], c["knowledge"], c["seed"])
                for *_, c in bench_protocol.cells(args)]

    def count(res, data):  # the runs "Still missing" names for one resolution and data, with no rows at all
        return sum(int(x.split(": ")[1].split(" of ")[0]) for x in make_protocol.missing([])
                   if x.startswith(f"- {data}, ") and f"{res} x {res}" in x)

    lego = runs(400, "lego")
    assert len(lego) == len(set(lego)) == count(400, "lego") == 3 * 3 * 8 * 3
    assert {r[0] for r in lego} == {"rsir", "paper", "calibrated"} and {r[1] for r in lego} == {16, 32, 64}
    assert ("calibrated", 16, "spikelik", "calibrated maps", 2) in lego
    assert not any(r[2] == "oracle" or (r[3] == "calibrated maps" and r[2] != "spikelik") for r in lego)
    # a method's calibrated-maps runs right after its true-maps ones
    assert lego[:6] == [("rsir", 16, "spikelik", k, s) for k in ("true maps", "calibrated maps") for s in (0, 1, 2)]
    chair = runs(100, "chair")
    assert len(chair) == count(100, "chair") == 7 * 3
    assert {(r[0], r[1]) for r in chair} == {("rsir", 64)} and "calibrated maps" not in {r[3] for r in chair}
    assert runs(400, "chair") == []  # the plan has no 400 x 400 procedural scene
    # without --plan the same request is every method, the oracle and the ideal sensor included
    assert len(runs(400, "lego", plan=False)) == 4 * 4 * len(bench_protocol.METHODS) * 3


def test_plan_with_nothing_to_make_says_so(tmp_path, monkeypatch, capsys):
    """A request the plan holds no run of makes nothing and says so in one line."""
    import bench_protocol
    monkeypatch.setattr(sys, "argv", ["bench_protocol.py", "--resolution", "100", "--data", "chair", "--sensors",
                                      "ideal", "--plan", "--out", str(tmp_path / "out"),
                                      "--results", str(tmp_path / "r.jsonl")])
    bench_protocol.main()
    assert capsys.readouterr().out == "no runs to make: the plan holds none of those asked for\n"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("jobs", [1, 2])
def test_no_run_starts_after_start_within(tmp_path, monkeypatch, capsys, jobs):
    """``--start-within S``: runs already started finish and are recorded; none starts after S seconds,
    and how many were left is said."""
    import time

    import bench_protocol

    def run_one(folder, cell, args):
        time.sleep(0.3)
        return {**cell, "train_seconds": 1.0, "metrics": {"psnr": 30.0, "psnr_object": 25.0}}

    monkeypatch.setattr(bench_protocol, "run_one", run_one)
    monkeypatch.setattr(bench_protocol, "dataset", lambda data, sensor, i, args: tmp_path / f"{data}_i{i}")
    results = tmp_path / "rows.jsonl"
    monkeypatch.setattr(sys, "argv", ["bench_protocol.py", "--resolution", "100", "--data", "chair", "--sensors", "rsir",
                                      "--intensities", "64", "--methods", "tfp32,tfi", "--seeds", "0,1,2",
                                      "--jobs", str(jobs), "--start-within", "0.1", "--results", str(results),
                                      "--out", str(tmp_path)])
    bench_protocol.main()
    assert len(results.read_text().splitlines()) == jobs  # the first run (or pair) only
    assert f"{6 - jobs} runs not started" in capsys.readouterr().out


def test_port_bias_section_averages_each_cell_over_its_runs():
    rate = {"kind": "rate", "intensity": 64, "x": 1.0, "subtractive": 0.25, "rsir": 0.2, "hard_reset": 0.2,
            "hard_reset_spread": {"0.1": 0.225}}

    def run(method, seed, saved, undone, gain):
        return {"kind": "run", "sensor": "paper", "intensity": 64, "method": method, "seed": seed,
                "psnr_object_saved": saved, "psnr_object_rate_loss_undone": {"0.1": undone, "0.05": undone - 1},
                "oracle_gain": gain, "psnr_object_oracle_gain": saved + 1}

    lines = make_protocol.port_bias_section([rate, run("spikenerf-paper", 2, 24.0, 26.0, 0.9),
                                             run("spikenerf-paper", 0, 25.0, 27.0, 0.8), run("spikelik", 1, 26.0, 25.0, 1.0)])
    assert "| 64 | 1 | 0.2500 | 0.2000 | 0.2000 | 0.2250 | 0.900 | 1.125 |" in lines
    header = next(line for line in lines if line.startswith("| sensor |"))
    assert "spread 0.05 | loss undone, spread 0.1 |" in header                    # spreads in numeric order
    assert "| paper | 64 | spikenerf-paper | 2 (0,2) | 24.50 | 25.50 | 26.50 | 0.850 | 25.50 |" in lines
    assert "| paper | 64 | spikelik | 1 (1) | 26.00 | 24.00 | 25.00 | 1.000 | 27.00 |" in lines
    assert make_protocol.port_bias_section([]) == []
    assert not any("Where the port's error lies" in line for line in lines)   # no run binned: no such table


def test_error_by_count_averages_the_bins_and_says_where_the_excess_is():
    def run(method, seed, saved, undone, pixels=(0.25, 0.75)):
        return {"kind": "run", "sensor": "paper", "intensity": 16, "method": method, "seed": seed,
                "psnr_object_saved": 20.0, "psnr_object_rate_loss_undone": {"0.1": 21.0},
                "oracle_gain": 1.0, "psnr_object_oracle_gain": 21.0,
                "by_expected_count": {"edges": [0, 1], "spread": 0.1, "pixels": list(pixels),
                                      "mse_saved": list(saved), "mse_undone": list(undone)}}

    lines = make_protocol.port_bias_section([
        run("spikenerf-paper", 0, (8e-4, 2e-4), (5e-4, 2e-4)), run("spikenerf-paper", 1, (6e-4, 2e-4), (7e-4, 2e-4)),
        run("spikelik", 0, (2e-4, 1e-4), (9e-4, 9e-4))])
    i = lines.index(next(line for line in lines if line.startswith("| sensor | I | runs port / default |")))
    assert lines[i] == "| sensor | I | runs port / default | | x I < 1 | ≥ 1 | all |"
    assert lines[i + 2] == "| paper | 16 | 2 / 1 | object pixels (%) | 25.0 | 75.0 | 100.0 |"
    assert lines[i + 3] == "| | | | default, as saved | 2.00 | 1.00 | 3.00 |"
    assert lines[i + 4] == "| | | | port, as saved | 7.00 | 2.00 | 9.00 |"
    assert lines[i + 5] == "| | | | port, loss undone | 6.00 | 2.00 | 8.00 |"
    assert lines[i + 6] == "| | | | port undone − default | 4.00 | 1.00 | 5.00 |"
    assert lines[i + 8] == ("The port's excess over the default, loss undone (x 10⁴): paper i16: +5.00 in all, +4.00 in "
                            "the 25.0 % of object pixels expecting under one spike (80 % of it).")
    lines = make_protocol.port_bias_section([run("spikenerf-paper", 0, (1e-4, 5e-4), (1e-4, 5e-4)),
                                             run("spikelik", 0, (2e-4, 1e-4), (2e-4, 1e-4))])
    assert lines[-2].endswith("paper i16: +3.00 in all, -1.00 in the 25.0 % of object pixels expecting under one "
                              "spike, the largest part at ≥ 1 (+4.00).")


def test_calibrated_maps_fitted_for_another_response_are_their_own_rows(tmp_path):
    """Calibrated maps are fitted for the camera's own response (bench_protocol: --kind rsir on the rsir
    camera, Eqs. S2-S6 on the others); rows from before the key were made with Eqs. S2-S6. On rsir those
    old rows are another run (key, folder) and another row of the tables, outside the third target."""
    import argparse

    import bench_protocol
    base = {**_row("spikelik", "calibrated maps", 24.0, iterations=9000), "field": bench_protocol.FIELD}
    fitted = {**base, "calibration_fit": "rsir", "metrics": {"psnr_object": 24.9}}
    assert bench_protocol.row_key(base) != bench_protocol.row_key(fitted)
    assert bench_protocol.row_key({**base, "calibration_fit": "if"}) == bench_protocol.row_key(base)
    true = {**base, "knowledge": "true maps", "metrics": {"psnr_object": 25.0}}
    assert bench_protocol.calibration_fit(true) is None
    paper = {**base, "sensor": "paper"}
    path = tmp_path / "rows.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in (base, fitted, true, paper)))
    rows = make_protocol.load(path)
    assert [r["knowledge"] for r in rows] == [make_protocol.MISFIT, "calibrated maps", "true maps", "calibrated maps"]
    line = next(x for x in make_protocol.targets(rows[:3]) if "| i64 |" in x)
    assert [c.strip() for c in line.split("|")[1:-1]][4] == "-0.10 (met; 1 of 3 seeds)"  # 24.9, not 24.0
    assert any(make_protocol.MISFIT in x and "24.00" in x for x in make_protocol.table(rows[:3], "psnr_object", "m"))
    # the runner asks for the camera's own fit, and --calibration-kind overrides it
    args = argparse.Namespace(data=["lego"], sensors=["rsir", "paper"], intensities=[64], methods=["spikelik"],
                              seeds=[0], calibrated=True, calibrated_methods=[], resolution=100, iters=0, frames=0,
                              batch_rays=2048, calibration_kind=None, plan=False, srgb_weight=None, ray_order="uniform")
    fits = {(c["sensor"], c.get("calibration_fit")) for *_, c in bench_protocol.cells(args)}
    assert fits == {("rsir", None), ("rsir", "rsir"), ("paper", None), ("paper", "if")}
    args.calibration_kind = "if"
    assert {c.get("calibration_fit") for *_, c in bench_protocol.cells(args)} == {None, "if"}
    # every method that uses the maps runs once more with calibrated ones, or (--calibrated-methods) the
    # ones named (the plan has spikelik alone: bench/gpu_session.sh's fill takes it from there with --plan)
    args.sensors, args.methods = ["paper"], ["spikelik", "spikenerf", "tfp32"]
    variants = {(c["method"], c["knowledge"]) for *_, c in bench_protocol.cells(args)}
    assert variants == {("spikelik", "true maps"), ("spikenerf", "true maps"), ("tfp32", "none"),
                        ("spikelik", "calibrated maps"), ("spikenerf", "calibrated maps")}
    args.calibrated_methods = ["spikelik"]
    variants = {(c["method"], c["knowledge"]) for *_, c in bench_protocol.cells(args)}
    assert variants == {("spikelik", "true maps"), ("spikenerf", "true maps"), ("tfp32", "none"),
                        ("spikelik", "calibrated maps")}
    # a method's calibrated-maps runs come right after its true-maps ones (a budget that stops the list
    # part-way, as the GPU's fill does, leaves that pair whole), seeds innermost
    args.calibrated_methods, args.seeds = [], [0, 1]
    order = [(c["method"], c["knowledge"], c["seed"]) for *_, c in bench_protocol.cells(args)]
    assert order == [("spikelik", "true maps", 0), ("spikelik", "true maps", 1),
                     ("spikelik", "calibrated maps", 0), ("spikelik", "calibrated maps", 1),
                     ("spikenerf", "true maps", 0), ("spikenerf", "true maps", 1),
                     ("spikenerf", "calibrated maps", 0), ("spikenerf", "calibrated maps", 1),
                     ("tfp32", "none", 0), ("tfp32", "none", 1)]
    assert ("spikelik", "calibrated maps") in make_protocol.PLANNED_LEGO
    assert ("spikenerf", "calibrated maps") not in make_protocol.PLANNED_LEGO


def _fake_trainer(calls: list):
    """bench_protocol._run in place of spikenerf train and eval: each command is appended to ``calls``, and the run
    folder gets what they would leave there (config.json, metrics.json)."""
    def fake_run(cmd):
        calls.append(cmd)
        run = Path(cmd[cmd.index("--out") + 1] if "--out" in cmd else cmd[2])
        run.mkdir(parents=True, exist_ok=True)
        (run / "config.json").write_text(json.dumps({"device_used": "cpu"}))
        (run / "metrics.json").write_text(json.dumps({"train_seconds": 1.0, "psnr": 30.0, "psnr_object": 25.0,
                                                      "per_view": []}))
        return ""
    return fake_run


def test_runs_with_an_srgb_weight_are_other_runs(tmp_path, monkeypatch):
    """The sRGB weight (``--srgb-weight``): a likelihood method's run takes the trainer's default (400 since
    2026-11-29) unless the call sets one, the runner always says it to the trainer, and its rows record it (rows
    without the key: 0, off, the default before). A run with the weight off keeps the folder name of the runs from
    before the key (so those resume), is its own key, fills no planned slot, and stands in the tables as its own
    method line (``spikelik --srgb-weight 0``, right after spikelik) with its own target line; the weighted run
    is the default's line and fills the slot."""
    import argparse

    import bench_protocol
    args = argparse.Namespace(data=["lego"], sensors=["rsir"], intensities=[64], methods=["spikelik", "tfp32"],
                              seeds=[0], calibrated=False, calibrated_methods=[], resolution=400, iters=0, frames=0,
                              batch_rays=2048, calibration_kind=None, plan=False, srgb_weight=None,
                              ray_order="uniform", out=tmp_path, device="cpu")
    cell, tfp = (c for *_, c in bench_protocol.cells(args))
    assert cell["srgb_weight"] == 400.0 and "srgb_weight" not in tfp
    calls = []
    monkeypatch.setattr(bench_protocol, "_run", _fake_trainer(calls))
    row = bench_protocol.run_one(tmp_path / "data", cell, args)
    train = calls[0]
    assert train[train.index("--srgb-weight") + 1] == "400" and train[train.index("--out") + 1].endswith("_srgbw400")
    assert row["srgb_weight"] == 400.0
    calls.clear()
    bench_protocol.run_one(tmp_path / "data", tfp, args)
    assert "--srgb-weight" not in calls[0]  # (the trainer refuses it for a method without the likelihood)
    args.srgb_weight = 0.0
    plain = next(bench_protocol.cells(args))[-1]
    assert plain["srgb_weight"] == 0.0
    calls.clear()
    bench_protocol.run_one(tmp_path / "data", plain, args)
    train = calls[0]
    assert train[train.index("--srgb-weight") + 1] == "0"  # said: the trainer's own default is 400
    assert train[train.index("--out") + 1].endswith("_9000_0_grid-fitted-box")

    base = {**_row("spikelik", "true maps", 25.0, iterations=9000), "field": bench_protocol.FIELD}
    weighted = {**base, "srgb_weight": 400.0, "metrics": {"psnr_object": 25.6}}
    assert bench_protocol.row_key(base) == bench_protocol.row_key({**base, "srgb_weight": 0.0})
    assert bench_protocol.row_key(weighted) != bench_protocol.row_key(base)
    path = tmp_path / "rows.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in (base, weighted)))
    rows = make_protocol.load(path)
    assert [r["method"] for r in rows] == ["spikelik --srgb-weight 0", "spikelik"]
    lines = make_protocol.table(rows + [{**base, "method": "spikenerf-paper"}], "psnr_object", "method")
    names = [x.split("|")[1].strip() for x in lines[2:]]
    assert names == ["spikelik", "spikelik --srgb-weight 0", "spikenerf-paper"]
    assert "25.60 (1)" in lines[2] and "25.00 (1)" in lines[3]
    targets = make_protocol.targets(rows + [{**base, "method": "spikenerf-paper", "metrics": {"psnr_object": 24.0}}])
    earlier = next(x for x in targets if "(the default before 2026-11-29)" in x)
    assert "| +1.00 (not met; 1 of 3 seeds) |" in earlier
    default = next(x for x in targets if "| lego, rsir, 400 x 400, 9000 it |" in x)
    assert "| +1.60 (not met; 1 of 3 seeds) |" in default

    def left(rs):
        line = next(x for x in make_protocol.missing(rs) if "lego, rsir, 400 x 400" in x)
        return int(line.split(": ")[1].split(" of ")[0])
    assert left(rows[:1]) == left([]) == left(rows[1:]) + 1


def test_runs_with_another_ray_order_are_other_runs(tmp_path, monkeypatch):
    """The ray order (``--ray-order``): the runner always says it to the trainer and its rows record it (rows without
    the key: uniform, the only order before 2026-12-02); a shuffled run is its own key in its own folder, and stands
    in the tables as its own method line (``spikelik --ray-order shuffled``) that the options section sets against
    the default's run of the same seed."""
    import argparse

    import bench_protocol
    args = argparse.Namespace(data=["lego"], sensors=["rsir"], intensities=[64], methods=["spikelik", "tfp32"],
                              seeds=[0], calibrated=False, calibrated_methods=[], resolution=400, iters=0, frames=0,
                              batch_rays=2048, calibration_kind=None, plan=False, srgb_weight=None,
                              ray_order="uniform", out=tmp_path, device="cpu")
    calls = []
    monkeypatch.setattr(bench_protocol, "_run", _fake_trainer(calls))
    uniform = [c for *_, c in bench_protocol.cells(args)]
    args.ray_order = "shuffled"
    shuffled = [c for *_, c in bench_protocol.cells(args)]
    assert [c["ray_order"] for c in uniform + shuffled] == ["uniform"] * 2 + ["shuffled"] * 2
    folders = []
    for cell in uniform + shuffled:
        calls.clear()
        row = bench_protocol.run_one(tmp_path / "data", cell, args)
        train = calls[0]
        assert train[train.index("--ray-order") + 1] == cell["ray_order"] == row["ray_order"]
        folders.append(train[train.index("--out") + 1])
    assert folders[0].endswith("_srgbw400") and folders[2] == folders[0] + "_shuffled"
    assert folders[3] == folders[1] + "_shuffled" and len(set(folders)) == 4

    base = {**_row("spikelik", "true maps", 25.0, iterations=9000), "field": bench_protocol.FIELD,
            "srgb_weight": 400.0, "metrics": {"psnr_object": 25.0, "psnr": 30.0, "ssim_object": 0.9}}
    other = {**base, "ray_order": "shuffled", "metrics": {"psnr_object": 25.2, "psnr": 30.1, "ssim_object": 0.91}}
    assert bench_protocol.row_key(base) == bench_protocol.row_key({**base, "ray_order": "uniform"})
    assert bench_protocol.row_key(other) != bench_protocol.row_key(base)
    path = tmp_path / "rows.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in (base, other)))
    rows = make_protocol.load(path)
    assert [r["method"] for r in rows] == ["spikelik", "spikelik --ray-order shuffled"]
    line = next(x for x in make_protocol.options_section(rows) if x.startswith("| lego, rsir, 400 x 400 |"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[2] == "spikelik --ray-order shuffled" and cells[5:8] == ["+0.20 (1)", "+0.10 (1)", "+0.010 (1)"]
    # its target line is set against the others drawn in its order, never against the uniform ones: none at first
    port = {**base, "method": "spikenerf-paper", "metrics": {"psnr_object": 24.0}}
    label = "lego, rsir, 400 x 400, 9000 it (spikelik --ray-order shuffled: not the default)"
    line = next(x for x in make_protocol.targets(rows + [port]) if label in x)
    assert [c.strip() for c in line.split("|")[1:-1]][2:] == ["–", "–", "–", "–"]
    line = next(x for x in make_protocol.targets(rows + [port, {**port, "method": "spikenerf-paper --ray-order shuffled",
                                                                 "metrics": {"psnr_object": 21.0}}]) if label in x)
    assert "| +4.20 (met; 1 of 3 seeds) |" in line  # 25.2 - 21.0, not 25.2 - 24.0


def test_the_plan_drawn_shuffled_is_made_and_counted_apart(tmp_path, monkeypatch):
    """``--plan --ray-order shuffled`` makes the plan's runs (no others) in that order, each once; make_protocol counts
    them apart from the default's plan: a uniform run fills no shuffled slot and a shuffled one no uniform slot,
    and a shuffled run with another option off its default (``--srgb-weight 0``) fills neither."""
    import bench_protocol

    results, made = tmp_path / "rows.jsonl", []

    def run_one(folder, cell, args):
        made.append(cell)
        return {**cell, "train_seconds": 1.0, "metrics": {"psnr": 30.0, "psnr_object": 25.0}}

    monkeypatch.setattr(bench_protocol, "run_one", run_one)
    monkeypatch.setattr(bench_protocol, "dataset", lambda data, sensor, i, args: tmp_path / f"{data}_i{i}")
    argv = ["bench_protocol.py", "--resolution", "100", "--data", "chair", "--sensors", "rsir,ideal", "--intensities",
            "32,64", "--methods", "spikelik,tfp32,oracle", "--seeds", "0,1", "--plan", "--ray-order", "shuffled",
            "--results", str(results), "--out", str(tmp_path)]
    monkeypatch.setattr(sys, "argv", argv)
    bench_protocol.main()
    assert sorted((c["method"], c["seed"]) for c in made) == [("spikelik", 0), ("spikelik", 1), ("tfp32", 0),
                                                               ("tfp32", 1)]  # the plan's: rsir, i64, no oracle
    assert {(c["sensor"], c["intensity"], c["ray_order"]) for c in made} == {("rsir", 64, "shuffled")}
    bench_protocol.main()  # all made: nothing more
    assert len(made) == 4 and len(results.read_text().splitlines()) == 4

    rows = make_protocol.load(results)
    assert {r["method"] for r in rows} == {"spikelik --ray-order shuffled", "tfp32 --ray-order shuffled"}

    def left(rs, order):
        gaps = [g for g in make_protocol.plan_gaps(rs, order) if g[:3] == (100, "chair", "rsir")]
        return len(gaps[0][6])

    assert left([], "shuffled") == left([], "uniform") == left(rows, "uniform") == 21
    assert left(rows, "shuffled") == 17
    uniform = [{**r, "method": r["method"].split(" ")[0]} for r in rows]  # the same runs drawn uniformly
    assert left(uniform, "shuffled") == 21 and left(uniform, "uniform") == 17
    weight_off = [{**r, "method": "spikelik --srgb-weight 0 --ray-order shuffled"} for r in rows
                  if r["method"].startswith("spikelik")]
    assert left(weight_off, "shuffled") == left(weight_off, "uniform") == 21
    assert sum(len(g[5]) for g in make_protocol.plan_gaps([])) == 537  # the whole plan, in either order
    assert "Made so far: 4 of the plan's 537 runs" in make_protocol.shuffled_plan_note(rows)


def test_order_summary_sets_each_planned_run_against_its_uniform_twin():
    """The summary of the plan drawn in both orders: per method, shuffled minus uniform seed for seed over the
    plan's cells, the cells gaining on every seed counted and those losing on every seed named; a seed made in one
    order only, a run at another budget and a method outside the plan (the oracle) are left out."""
    def row(method, seed, obj, intensity=64, iterations=9000, knowledge="true maps"):
        return _row(method, knowledge, obj, seed=seed, intensity=intensity, iterations=iterations)

    shuffled = " --ray-order shuffled"
    rows = [row("spikelik", s, 25.0 + 0.1 * s) for s in range(3)]
    rows += [row("spikelik" + shuffled, s, 25.2 + 0.1 * s) for s in range(3)]        # +0.2 on every seed
    rows += [row("spikelik", s, 20.0, intensity=16) for s in range(3)]
    rows += [row("spikelik" + shuffled, s, 19.9, intensity=16) for s in range(2)]     # -0.1 on both seeds made
    rows += [row("tfp32", s, 20.0, knowledge="none") for s in range(2)]
    rows += [row("tfp32" + shuffled, 0, 20.5, knowledge="none"), row("tfp32" + shuffled, 1, 19.5, knowledge="none")]
    rows += [row("spikelik", 0, 10.0, iterations=3000), row("spikelik" + shuffled, 0, 30.0, iterations=3000)]
    rows += [row("oracle", 0, 26.0, knowledge="ground-truth images"),
             row("oracle" + shuffled, 0, 27.0, knowledge="ground-truth images")]
    table = make_protocol.order_summary(rows)
    cells = {c[0]: c for c in ([x.strip() for x in line.split("|")[1:-1]] for line in table[2:])}
    assert set(cells) == {"spikelik", "tfp32"}
    diffs = np.array([0.2] * 3 + [-0.1] * 2)
    assert cells["spikelik"][1:] == ["true maps", "2 / 0", "5", f"{diffs.mean():+.2f} ± {diffs.std(ddof=1):.2f}",
                                     "1 of 2", "1: lego, rsir, 400 x 400, i16"]
    assert cells["tfp32"][1:] == ["none", "1 / 0", "2", "+0.00 ± 0.71", "0 of 1", "0"]
    assert make_protocol.order_summary([r for r in rows if shuffled not in r["method"]]) == []


def test_options_section_pairs_each_run_with_the_default_run_of_its_seed():
    """A run with a trainer option is set against the same method's default run of its seed (same data,
    knowledge, budget, intensity): mean and SD of the per-seed differences; a seed with no default twin, or a
    twin at another budget, is left out."""
    def row(method, seed, obj, iterations=9000):
        r = _row(method, "true maps", obj, seed=seed, iterations=iterations)
        return {**r, "metrics": {"psnr_object": obj, "psnr": obj + 5, "ssim_object": obj / 100}}

    rows = [row("spikelik", s, 25.0 + 0.1 * s) for s in range(2)]
    rows += [row("spikelik --srgb-weight 400", s, 25.5 + 0.3 * s) for s in range(3)]  # seed 2: no default twin
    rows += [row("spikelik", 2, 20.0, iterations=3000)]  # another budget: not seed 2's twin
    lines = make_protocol.options_section(rows)
    line = next(x for x in lines if x.startswith("| lego, rsir, 400 x 400 |"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[2:5] == ["spikelik --srgb-weight 400", "true maps", "i64"]
    assert cells[5] == "+0.60 ± 0.14 (2)" and cells[6] == "+0.60 ± 0.14 (2)" and cells[7] == "+0.006 ± 0.001 (2)"
    assert make_protocol.options_section(rows[:2]) == []  # no option off its default: no section


def test_short_streams_take_the_unweighted_default_and_their_weighted_rows_are_labelled(tmp_path):
    """Where a white pixel counts fewer than 16 spikes a window (the first 32 frames at i64: 8), the trainer's
    default weight is 0: the runner's cell there is unweighted, at 64 frames (16 spikes) or i16 with all 256 (16)
    weighted; the tables name an unweighted short-stream row ``spikelik`` (the default's) and a weighted one
    ``spikelik --srgb-weight 400``, while at 64 frames the unweighted row is ``spikelik --srgb-weight 0``."""
    import argparse

    import bench_protocol

    def cell(frames, intensity=64):
        args = argparse.Namespace(data=["lego"], sensors=["rsir"], intensities=[intensity], methods=["spikelik"],
                                  seeds=[0], calibrated=False, calibrated_methods=[], resolution=400, iters=0,
                                  frames=frames, batch_rays=2048, calibration_kind=None, plan=False, srgb_weight=None,
                                  ray_order="uniform",
                                  out=tmp_path, device="cpu")
        return next(bench_protocol.cells(args))[-1]

    assert cell(32)["srgb_weight"] == 0.0 and cell(64)["srgb_weight"] == 400.0
    assert cell(0, intensity=16)["srgb_weight"] == 400.0 and cell(128, intensity=16)["srgb_weight"] == 0.0
    base = {**_row("spikelik", "true maps", 25.0, iterations=9000), "field": bench_protocol.FIELD}
    rows = [dict(base, frames=32), dict(base, frames=32, srgb_weight=400.0), dict(base, frames=64),
            dict(base, frames=64, srgb_weight=400.0), dict(base, frames=32, windows=1, srgb_weight=0.0)]
    path = tmp_path / "rows.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert [r["method"] for r in make_protocol.load(path)] == [
        "spikelik", "spikelik --srgb-weight 400", "spikelik --srgb-weight 0", "spikelik", "spikelik"]
