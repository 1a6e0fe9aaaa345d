"""Bad input a user can give, each through the real command line (issue 6, "Bad input").

Every case: exit code != 0, stderr is exactly one line that names the problem's file (or
option), no traceback, and no file under the test folder is created, removed or rewritten
(compared by content, inode and mtime).

Problems that only show inside a view's pixels (a truncated PNG, NaN/Inf/negative EXR
radiance, a full disk) are found while converting; there the views finished before the bad
one are kept, complete, for resume (docs/scaling.md): ``test_bad_view_content`` checks that
nothing partial is left, nothing existing is changed, no manifest claims a finished dataset,
and a rerun after fixing the input ends with the bytes of a clean run.
"""
from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from _scale_helpers import make_nerf, make_render, run_spikegen, tree
from spikegen.cli import main
from spikegen.dataset import convert
from spikegen.spikeio import write_exr

NAME = "src_i32"  # dataset folder of a NeRF source folder named "src" at intensity 32
SIZE = 16  # 16 x 16 images: 256 pixels, 32 bytes a frame
FRAMES = 16


# ---------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def templates(tmp_path_factory):
    """A NeRF source, a render source and a finished dataset, copied into each case."""
    base = tmp_path_factory.mktemp("templates")
    nerf = make_nerf(base / "src", views=3, size=SIZE, seed=1)
    render = make_render(base / "render", views=2, size=SIZE, subframes=2, seed=2)
    convert(nerf, base / "data", [32], sensor="paper", frames=FRAMES, progress=False)
    return base


@pytest.fixture()
def work(templates, tmp_path):
    for name in ("src", "render", "data"):
        shutil.copytree(templates / name, tmp_path / name)
    return tmp_path


def snapshot(root: Path) -> dict:
    out = {}
    for p in sorted(root.rglob("*")):
        st = p.lstat()
        out[p.relative_to(root).as_posix()] = (p.is_dir(), st.st_ino, st.st_mtime_ns, st.st_size,
                                               None if p.is_dir() else tree_hash(p))
    return out


def tree_hash(p: Path) -> str:
    import hashlib

    return hashlib.sha256(p.read_bytes()).hexdigest()


def run_main(argv, capsys) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def edit_json(path: Path, fn) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))


def conv(src, out, *extra):
    return ["convert", src, "--intensity", "32", "--frames", FRAMES, "--out", out, *extra]


# ---------------------------------------------------------------------- cases
# Each case takes the work folder and returns (argv, needle): needle must appear in stderr.
CASES = {}


def case(fn):
    CASES[fn.__name__] = fn
    return fn


# --- convert: the source folder
@case
def source_missing(w):
    return conv(w / "nope", w / "out"), "nope"


@case
def source_not_a_dataset(w):
    (w / "empty").mkdir()
    return conv(w / "empty", w / "out"), "empty"


@case
def transforms_not_json(w):
    (w / "src/transforms_train.json").write_text("{not json")
    return conv(w / "src", w / "out"), "transforms_train.json"


@case
def transforms_not_an_object(w):
    (w / "src/transforms_train.json").write_text("[1, 2, 3]")
    return conv(w / "src", w / "out"), "transforms_train.json"


@case
def transforms_empty_frames(w):
    edit_json(w / "src/transforms_train.json", lambda d: d.update(frames=[]))
    return conv(w / "src", w / "out"), "non-empty list 'frames'"


@case
def transforms_no_camera_angle(w):
    edit_json(w / "src/transforms_train.json", lambda d: d.pop("camera_angle_x"))
    return conv(w / "src", w / "out"), "camera_angle_x"


@case
def transforms_frame_without_file_path(w):
    edit_json(w / "src/transforms_train.json", lambda d: d["frames"][1].pop("file_path"))
    return conv(w / "src", w / "out"), "transforms_train.json"


@case
def transforms_matrix_not_4x4(w):
    edit_json(w / "src/transforms_train.json", lambda d: d["frames"][2].update(transform_matrix=[[1, 0], [0, 1]]))
    return conv(w / "src", w / "out"), "transforms_train.json"


@case
def transforms_matrix_nan(w):
    def nan(d):
        d["frames"][0]["transform_matrix"][0][3] = float("nan")
    edit_json(w / "src/transforms_train.json", nan)
    return conv(w / "src", w / "out"), "transforms_train.json"


@case
def png_missing(w):
    (w / "src/train/r_2.png").unlink()
    return conv(w / "src", w / "out"), "r_2.png"


@case
def png_corrupt(w):
    (w / "src/train/r_1.png").write_bytes(b"this is not a PNG file at all" * 4)
    return conv(w / "src", w / "out"), "r_1.png"


@case
def png_other_size(w):
    Image.new("RGBA", (SIZE * 2, SIZE)).save(w / "src/train/r_2.png")
    return conv(w / "src", w / "out"), "r_2.png"


# --- convert: a render folder
@case
def render_wrong_format(w):
    edit_json(w / "render/render.json", lambda d: d.update(format="something-else/2"))
    return conv(w / "render", w / "out"), "render.json"


@case
def render_missing_field(w):
    edit_json(w / "render/render.json", lambda d: d.pop("subframes"))
    return conv(w / "render", w / "out"), "render.json"


@case
def render_splits_not_a_mapping(w):
    edit_json(w / "render/render.json", lambda d: d.update(splits=[1, 2]))
    return conv(w / "render", w / "out"), "render.json"


@case
def render_view_not_an_object(w):
    edit_json(w / "render/render.json", lambda d: d["splits"]["train"].append("r_9"))
    return conv(w / "render", w / "out"), "render.json"


@case
def render_wrong_subframe_count(w):
    edit_json(w / "render/render.json", lambda d: d["splits"]["train"][1]["subframe_transform_matrices"].pop())
    return conv(w / "render", w / "out"), "render.json"


@case
def render_no_views(w):
    edit_json(w / "render/render.json", lambda d: d.update(splits={"train": []}))
    return conv(w / "render", w / "out"), "render.json"


@case
def exr_missing(w):
    (w / "render/train/r_1_sub01.exr").unlink()
    return conv(w / "render", w / "out"), "r_1_sub01.exr"


@case
def exr_corrupt(w):
    (w / "render/train/r_1_sub00.exr").write_bytes(b"v/1\x01" + b"\x00garbage" * 20)
    return conv(w / "render", w / "out"), "r_1_sub00.exr"


@case
def exr_other_size(w):
    write_exr(w / "render/train/r_1_sub01.exr", np.ones((SIZE, SIZE // 2, 4), np.float32))
    return conv(w / "render", w / "out"), "r_1_sub01.exr"


# --- convert: option values
@case
def intensity_zero(w):
    return ["convert", w / "src", "--intensity", "0", "--out", w / "out"], "--intensity"


@case
def intensity_negative(w):
    return ["convert", w / "src", "--intensity=-16", "--out", w / "out"], "--intensity"


@case
def intensity_nan(w):
    return ["convert", w / "src", "--intensity", "nan", "--out", w / "out"], "--intensity"


@case
def intensity_not_a_number(w):
    return ["convert", w / "src", "--intensity", "bright", "--out", w / "out"], "--intensity"


@case
def intensity_absurd(w):
    return ["convert", w / "src", "--intensity", "1e9", "--out", w / "out"], "--intensity"


@case
def frames_zero(w):
    return ["convert", w / "src", "--intensity", "32", "--frames", "0", "--out", w / "out"], "--frames"


@case
def resolution_too_small(w):
    return conv(w / "src", w / "out", "--resolution", "4"), "--resolution"


@case
def resolution_not_whole_bytes(w):
    return conv(w / "src", w / "out", "--resolution", "9"), "9x9"


@case
def workers_zero(w):
    return conv(w / "src", w / "out", "--workers", "0"), "--workers"


@case
def sensor_unknown(w):
    return conv(w / "src", w / "out", "--sensor", "bogus"), "bogus"


@case
def sensor_json_not_json(w):
    (w / "bad_sensor.json").write_text("{")
    return conv(w / "src", w / "out", "--sensor", w / "bad_sensor.json"), "bad_sensor.json"


@case
def sensor_json_wrong_format(w):
    (w / "bad_sensor.json").write_text(json.dumps({"format": "other", "parameters": {}}))
    return conv(w / "src", w / "out", "--sensor", w / "bad_sensor.json"), "bad_sensor.json"


@case
def sensor_json_bad_parameter(w):
    doc = json.loads((w / "data" / NAME / "sensor.json").read_text())
    doc["parameters"]["reset"] = "explode"
    doc["maps"] = None
    (w / "s.json").write_text(json.dumps(doc))
    return conv(w / "src", w / "out", "--sensor", w / "s.json"), "s.json"


@case
def sensor_maps_missing(w):
    shutil.copy(w / "data" / NAME / "sensor.json", w / "lonely.json")  # names sensor.npz, not copied
    return conv(w / "src", w / "out", "--sensor", w / "lonely.json"), "sensor.npz"


@case
def scheduler_unreachable(w):
    return conv(w / "src", w / "out", "--scheduler", "tcp://127.0.0.1:9"), "--scheduler"


# --- convert: the output folder
@case
def out_is_a_file(w):
    (w / "occupied").write_text("a file where a folder should be")
    return conv(w / "src", w / "occupied"), "occupied"


@case
def out_unwritable(w):
    if os.geteuid() == 0:  # root writes anywhere a permission bit forbids; sysfs refuses everyone
        return conv(w / "src", "/sys/spikegen-test-out"), "/sys/spikegen-test-out"
    (w / "locked").mkdir(mode=0o500)
    return conv(w / "src", w / "locked"), "locked"


@case
def out_holds_other_parameters(w):
    return ["convert", w / "src", "--intensity", "32", "--frames", FRAMES, "--seed", "7", "--out", w / "data"], NAME


@case
def out_holds_foreign_files(w):
    (w / "out" / NAME).mkdir(parents=True)
    (w / "out" / NAME / "notes.txt").write_text("mine")
    return conv(w / "src", w / "out"), NAME


# --- render (checked before Blender is started or anything is written)
def rend(w, *extra):
    return ["render", "--intensity", "32", "--out", w / "out", *extra]


@case
def render_unknown_scene(w):
    return rend(w, "--scene", "teapot"), "teapot"


@case
def render_no_scene(w):
    return rend(w), "--scene"


@case
def render_scene_and_blend(w):
    return rend(w, "--scene", "lego", "--blend", w / "x.blend"), "--blend"


@case
def render_blend_missing(w):
    return rend(w, "--blend", w / "missing.blend"), "missing.blend"


@case
def render_views_malformed(w):
    return rend(w, "--scene", "lego", "--views", "10,10"), "--views"


@case
def render_views_all_zero(w):
    return rend(w, "--scene", "lego", "--views", "0,0,0"), "--views"


@case
def render_subframes_zero(w):
    return rend(w, "--scene", "lego", "--subframes", "0"), "--subframes"


@case
def render_resolution_too_small(w):
    return rend(w, "--scene", "lego", "--resolution", "4"), "--resolution"


@case
def render_samples_zero(w):
    return rend(w, "--scene", "lego", "--samples", "0"), "--samples"


@case
def render_intensity_absurd(w):
    return ["render", "--scene", "lego", "--intensity", "1e12", "--out", w / "out"], "--intensity"


@case
def render_barrel_lens(w):
    return rend(w, "--scene", "lego", "--lens-k1", "-0.2"), "barrel lens"


@case
def convert_barrel_lens(w):
    return conv(w / "render", w / "out", "--lens-k1", "-0.1"), "barrel lens"


@case
def convert_lens_not_finite(w):
    return conv(w / "src", w / "out", "--lens-k1", "nan"), "--lens-k1"


# --- verify
@case
def verify_missing_folder(w):
    return ["verify", w / "nothere"], "nothere"


@case
def verify_no_manifest(w):
    (w / "data" / NAME / "manifest.json").unlink()
    return ["verify", w / "data" / NAME], NAME


@case
def verify_manifest_not_json(w):
    (w / "data" / NAME / "manifest.json").write_text("{{{")
    return ["verify", w / "data" / NAME], "manifest.json"


@case
def verify_file_missing(w):
    (w / "data" / NAME / "train/r_1.dat").unlink()
    return ["verify", w / "data" / NAME], "train/r_1.dat"


@case
def verify_dat_truncated(w):
    p = w / "data" / NAME / "train/r_0.dat"
    p.write_bytes(p.read_bytes()[:-5])
    return ["verify", w / "data" / NAME], "r_0.dat"


@case
def verify_dat_oversized(w):
    p = w / "data" / NAME / "train/r_2.dat"
    p.write_bytes(p.read_bytes() + b"\x00" * 32)
    return ["verify", w / "data" / NAME], "r_2.dat"


@case
def verify_png_altered(w):
    p = w / "data" / NAME / "train/r_0.png"
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0x01
    p.write_bytes(bytes(data))
    return ["verify", w / "data" / NAME], "r_0.png"


@case
def verify_stale_manifest(w):
    # transforms edited after the manifest was written: the manifest no longer describes it
    p = w / "data" / NAME / "transforms_train.json"
    p.write_text(p.read_text().replace("0.6911112070083618", "0.6911112070083619"))  # same size, new content
    return ["verify", w / "data" / NAME], "transforms_train.json"


@case
def verify_leftover_part_file(w):
    (w / "data" / NAME / "train/.r_1.dat.x1y2.part").write_bytes(b"\x00" * 7)
    return ["verify", w / "data" / NAME], ".r_1.dat.x1y2.part"


# --- info / preview
def dat(w) -> Path:
    return w / "data" / NAME / "train/r_0.dat"


@case
def info_missing_file(w):
    return ["info", w / "none.dat", "--size", "16x16"], "none.dat"


@case
def info_dat_without_size(w):  # outside a dataset folder: no config.yaml to give the size
    loose = w / "loose.dat"
    shutil.copyfile(dat(w), loose)
    return ["info", loose], "loose.dat"


@case
def info_dat_truncated(w):
    p = w / "cut.dat"
    p.write_bytes(dat(w).read_bytes()[:-3])
    return ["info", p, "--size", "16x16"], "cut.dat"


@case
def info_dat_oversized(w):
    p = w / "long.dat"
    p.write_bytes(dat(w).read_bytes() + b"\x01\x02\x03")
    return ["info", p, "--size", "16x16"], "long.dat"


@case
def info_wrong_size(w):
    return ["info", dat(w), "--size", "24x24"], "r_0.dat"  # 24*24/8 = 72 bytes do not divide 512


@case
def info_size_not_whole_bytes(w):
    return ["info", dat(w), "--size", "15x15"], "r_0.dat"


@case
def info_size_malformed(w):
    return ["info", dat(w), "--size", "sixteen"], "--size"


@case
def info_size_negative(w):
    return ["info", dat(w), "--size", "-16x16"], "--size"


@case
def info_unknown_extension(w):
    p = w / "spikes.txt"
    p.write_text("0101")
    return ["info", p], "spikes.txt"


@case
def info_npz_corrupt(w):
    p = w / "broken.npz"
    p.write_bytes(b"PK\x03\x04 not really a zip")
    return ["info", p], "broken.npz"


@case
def info_npy_float(w):
    p = w / "float.npy"
    np.save(p, np.full((4, 8, 8), 0.5))
    return ["info", p], "float.npy"


@case
def info_npy_not_binary(w):
    p = w / "counts.npy"
    np.save(p, np.full((4, 8, 8), 2, dtype=np.uint8))
    return ["info", p], "counts.npy"


@case
def info_npy_wrong_rank(w):
    p = w / "flat.npy"
    np.save(p, np.zeros((8, 8), dtype=np.uint8))
    return ["info", p], "flat.npy"


@case
def preview_out_not_png(w):
    return ["preview", dat(w), "--size", "16x16", "--out", w / "pic.jpg"], "pic.jpg"


@case
def preview_window_zero(w):
    return ["preview", dat(w), "--size", "16x16", "--window", "0", "--out", w / "pic.png"], "--window"


@case
def preview_out_unwritable(w):
    (w / "blocker").write_text("x")
    return ["preview", dat(w), "--size", "16x16", "--out", w / "blocker/pic.png"], "blocker"


# ---------------------------------------------------------------------- tests
def check_one_line(code, err, needle):
    assert code != 0, f"exit code 0, stderr {err!r}"
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {lines!r}"
    assert needle in lines[0], f"{needle!r} not named in {lines[0]!r}"


KNOWN_GAPS: dict = {}  # cases that document a known gap (strict xfail); none open


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.xfail(reason=KNOWN_GAPS[n], strict=True))
                                  if n in KNOWN_GAPS else n for n in sorted(CASES)])
def test_bad_input_one_line_nothing_written(name, work, capsys):
    argv, needle = CASES[name](work)
    before = snapshot(work)
    code, out, err = run_main(argv, capsys)
    check_one_line(code, err, needle)
    after = snapshot(work)
    assert after == before, f"files changed: {sorted(set(after.items()) ^ set(before.items()))[:6]}"


def test_every_case_is_its_own_kind(templates, tmp_path, capsys):
    """The cases are distinct kinds of bad input: run each on its own copy, no two give the same
    message (their folder aside), and there are at least 30 different messages."""
    messages = {}
    for name in sorted(CASES):
        w = tmp_path / name
        for sub in ("src", "render", "data"):
            shutil.copytree(templates / sub, w / sub)
        argv, _ = CASES[name](w)
        _, _, err = run_main(argv, capsys)
        messages.setdefault(err.strip().replace(str(w), "<case>"), []).append(name)
    alike = sorted(names for names in messages.values() if len(names) > 1)
    assert alike == [], f"cases that give the same message: {alike}"
    assert len(messages) >= 30


# A few cases through the installed console script in a fresh process: what a user sees.
@pytest.mark.parametrize("name", ["transforms_not_json", "png_corrupt", "exr_other_size", "intensity_absurd",
                                  "verify_dat_truncated", "info_dat_oversized", "out_holds_other_parameters"])
def test_bad_input_real_process(name, work):
    argv, needle = CASES[name](work)
    before = snapshot(work)
    proc = run_spikegen(*argv, timeout=60)
    check_one_line(proc.returncode, proc.stderr, needle)
    assert snapshot(work) == before


@pytest.mark.blender
def test_render_blend_not_a_blend_file(work):
    """A --blend that Blender cannot open (needs bpy; Blender may print its own note on stdout)."""
    pytest.importorskip("bpy")
    (work / "notes.blend").write_text("not a blend file")
    before = snapshot(work)
    proc = run_spikegen("render", "--blend", work / "notes.blend", "--intensity", "32", "--out", work / "out",
                        timeout=120)
    check_one_line(proc.returncode, proc.stderr, "notes.blend")
    assert snapshot(work) == before


RENDER_LATE_CHECKS = {  # conversion options `render` must check before Blender starts
    "render_workers_zero": (["--workers", "0"], "--workers"),
    "render_sensor_unknown": (["--sensor", "bogus"], "bogus"),
}


@pytest.mark.blender
@pytest.mark.parametrize("name", sorted(RENDER_LATE_CHECKS))
def test_render_checks_conversion_options_before_rendering(name, work, capsys):
    pytest.importorskip("bpy")
    extra, needle = RENDER_LATE_CHECKS[name]
    before = snapshot(work)
    code, out, err = run_main(["render", "--scene", "lego", "--views", "1,0,0", "--resolution", "16",
                               "--subframes", "1", "--frames", "8", "--engine", "workbench", "--intensity", "32",
                               "--out", work / "out", *extra], capsys)
    check_one_line(code, err, needle)
    assert snapshot(work) == before


# ---------------------------------------------------------------------- problems inside a view's pixels
def _png_truncated(w):
    p = w / "src/train/r_2.png"
    good = p.read_bytes()
    p.write_bytes(good[: len(good) // 2])
    return "src", "r_2.png", lambda: p.write_bytes(good)


def _exr_values(value):
    def setup(w):
        p = w / "render/train/r_1_sub01.exr"
        good = p.read_bytes()
        arr = np.ones((SIZE, SIZE, 4), np.float32) * 0.5
        arr[3, 5, 1] = value
        write_exr(p, arr)
        return "render", "r_1_sub01.exr", lambda: p.write_bytes(good)
    return setup


def _exr_pixels_corrupt(w):
    p = w / "render/train/r_1_sub00.exr"
    good = p.read_bytes()
    p.write_bytes(good[: len(good) - 40])  # header intact, pixel data cut short
    return "render", "r_1_sub00.exr", lambda: p.write_bytes(good)


CONTENT_CASES = {
    "png_truncated_pixels": _png_truncated,
    "exr_nan": _exr_values(float("nan")),
    "exr_inf": _exr_values(float("inf")),
    "exr_negative": _exr_values(-0.25),
    "exr_pixels_corrupt": _exr_pixels_corrupt,
}


def _dataset_files_ok(folder: Path, frames: int, pixels: int) -> None:
    """Nothing partial: no temporaries, no manifest, every .dat complete."""
    names = [p.name for p in folder.rglob("*")]
    assert not [n for n in names if n.endswith(".part")], names
    assert "manifest.json" not in names
    for p in folder.rglob("*.dat"):
        assert p.stat().st_size == frames * pixels // 8


@pytest.mark.parametrize("name", sorted(CONTENT_CASES))
def test_bad_view_content(name, work, capsys, tmp_path_factory):
    src, needle, repair = CONTENT_CASES[name](work)
    before = snapshot(work)
    code, out, err = run_main(conv(work / src, work / "out"), capsys)
    check_one_line(code, err, needle)
    after = snapshot(work)
    assert {k: v for k, v in after.items() if k in before} == before, "an existing file was changed"
    new = sorted(set(after) - set(before))
    assert all(k == "out" or k.startswith("out/") for k in new), new
    _dataset_files_ok(work / "out", FRAMES, SIZE * SIZE)
    # fix the input and rerun: the same bytes as a clean run of the good source
    repair()
    assert run_main(conv(work / src, work / "out"), capsys)[0] == 0
    clean = tmp_path_factory.mktemp("clean")
    shutil.copytree(work / src, clean / src)
    assert run_main(conv(clean / src, clean / "out"), capsys)[0] == 0
    assert tree(work / "out") == tree(clean / "out")
    assert run_main(["verify", next((work / "out").iterdir())], capsys)[0] == 0


def test_disk_full_while_writing(work, capsys, monkeypatch):
    """ENOSPC from the file system (simulated at fsync): one line, the file named, no temporary left."""
    import spikegen.spikeio as sio

    real_fsync = os.fsync

    def full_for_spikes(fd):
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".part") and ".r_1.dat." in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(sio.os, "fsync", full_for_spikes)
    code, out, err = run_main(conv(work / "src", work / "out"), capsys)
    check_one_line(code, err, "r_1.dat")
    assert "No space left" in err
    _dataset_files_ok(work / "out", FRAMES, SIZE * SIZE)
    assert (work / "out" / NAME / "train/r_0.dat").is_file()  # the view before is kept for resume
    monkeypatch.setattr(sio.os, "fsync", real_fsync)
    assert run_main(conv(work / "src", work / "out"), capsys)[0] == 0
    assert run_main(["verify", work / "out" / NAME], capsys)[0] == 0


def test_file_size_limit_in_real_process(work):
    """A real write failure in a real process (RLIMIT_FSIZE, EFBIG): one line naming the file, no
    temporary or half file left, and a rerun without the limit finishes the dataset."""
    limit = 3000  # bytes: the JSON files fit, a 16-frame 16x16 .dat (512 B) fits, sensor.npz does not

    def limited():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = run_spikegen(*conv(work / "src", work / "out"), "--frames", "512", timeout=60, preexec_fn=limited)
    check_one_line(proc.returncode, proc.stderr, ".dat")
    assert "too large" in proc.stderr.lower()
    _dataset_files_ok(work / "out", 512, SIZE * SIZE)
    assert run_spikegen(*conv(work / "src", work / "out"), "--frames", "512", timeout=60).returncode == 0
    assert run_spikegen("verify", work / "out" / NAME).returncode == 0
