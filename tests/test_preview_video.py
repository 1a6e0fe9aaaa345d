"""spikegen preview --out X.gif / X.mp4: the spike stream as an animation of TFP over sliding
windows; the PNG preview as before; bad input; nothing left behind by an interrupted write."""
import numpy as np
import pytest
from PIL import Image

from spikegen.animation import write_animation
from spikegen.cli import main
from spikegen.preview import preview_image
from spikegen.spikeio import linear_to_srgb, write_spikes

T, H, W = 64, 6, 20


@pytest.fixture()
def stream(tmp_path):
    """A bright bar moving right one column every 4 frames over a dim, seeded random background."""
    rng = np.random.default_rng(7)
    s = (rng.random((T, H, W)) < 0.05).astype(np.uint8)
    for t in range(T):
        s[t, :, t // 4] = 1
    path = tmp_path / "bar.npz"
    write_spikes(path, s)
    return path, s


def _frames(path):
    with Image.open(path) as im:
        out = []
        for k in range(im.n_frames):
            im.seek(k)
            out.append(np.asarray(im.convert("L")))
        return out, im.info


def _expected_frame(s, a, window):
    """TFP over frames a..a+window, the whole stream's 99.5th-percentile rate as white, sRGB, 8 bits."""
    white = np.percentile(s.mean(axis=0, dtype=np.float64), 99.5)
    rate = s[a:a + window].sum(axis=0) / window
    return np.round(linear_to_srgb(np.clip(rate / white, 0, 1)) * 255).astype(np.uint8)


def test_gif_frames_are_tfp_over_sliding_windows(stream, tmp_path, capsys):
    path, s = stream
    out = tmp_path / "bar.gif"
    assert main(["preview", str(path), "--out", str(out)]) == 0  # defaults: window 16, step 4, 10 fps
    frames, info = _frames(out)
    starts = range(0, T - 16 + 1, 4)
    assert len(frames) == len(starts) == 13 and frames[0].shape == (H, W)
    for k, a in enumerate(starts):
        np.testing.assert_array_equal(frames[k], _expected_frame(s, a, 16))
    assert info["duration"] == 100 and info["loop"] == 0
    bar_col = [int(np.argmax(f.mean(axis=0))) for f in frames]
    assert bar_col == sorted(bar_col) and bar_col[-1] > bar_col[0]  # the bar moves right
    assert "13 frames" in capsys.readouterr().out


def test_window_step_and_fps(stream, tmp_path):
    path, s = stream
    out = tmp_path / "w8.gif"
    assert main(["preview", str(path), "--out", str(out), "--window", "8", "--step", "8", "--fps", "25"]) == 0
    frames, info = _frames(out)
    assert len(frames) == 8 and info["duration"] == 40
    np.testing.assert_array_equal(frames[3], _expected_frame(s, 24, 8))


def test_png_preview_is_unchanged(stream, tmp_path):
    path, s = stream
    out = tmp_path / "bar.png"
    assert main(["preview", str(path), "--out", str(out), "--window", "16"]) == 0
    np.testing.assert_array_equal(np.asarray(Image.open(out)), preview_image(s, 16))


def test_mp4(stream, tmp_path):
    ffmpeg = pytest.importorskip("imageio_ffmpeg")
    path, _ = stream
    out = tmp_path / "bar.mp4"
    assert main(["preview", str(path), "--out", str(out), "--step", "16"]) == 0
    reader = ffmpeg.read_frames(str(out))
    meta = next(reader)
    assert sum(1 for _ in reader) == 4 and tuple(meta["size"]) == (W, H) and meta["fps"] == 10
    again = tmp_path / "again.mp4"
    assert main(["preview", str(path), "--out", str(again), "--step", "16"]) == 0
    assert again.read_bytes() == out.read_bytes()  # the same frames give the same file


@pytest.mark.parametrize("args,needle", [
    (["--out", "{d}/bar.avi"], "bar.avi"),
    (["--out", "{d}/bar.gif", "--step", "0"], "--step"),
    (["--out", "{d}/bar.gif", "--window", "0"], "--window"),
    (["--out", "{d}/bar.gif", "--fps", "0"], "--fps"),
    (["--out", "{d}/bar.gif", "--fps", "500"], "--fps"),
])
def test_bad_input_is_one_line_and_writes_nothing(stream, tmp_path, capsys, args, needle):
    path, _ = stream
    d = tmp_path / "out"
    assert main(["preview", str(path), *[a.format(d=d) for a in args]]) != 0
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err, err
    assert not d.exists()


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_an_interrupted_write_leaves_nothing(tmp_path, suffix):
    if suffix == ".mp4":
        pytest.importorskip("imageio_ffmpeg")

    def frames():
        yield np.zeros((8, 8), np.uint8)
        yield np.full((8, 8), 255, np.uint8)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_animation(tmp_path / f"a{suffix}", frames(), 10)
    assert list(tmp_path.iterdir()) == []


def test_mp4_without_an_encoder_is_one_line(stream, tmp_path, capsys, monkeypatch):
    import spikegen.animation

    monkeypatch.setattr(spikegen.animation, "_ffmpeg", lambda: None)  # as if imageio-ffmpeg were not installed
    path, _ = stream
    assert main(["preview", str(path), "--out", str(tmp_path / "o" / "bar.mp4")]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "imageio-ffmpeg" in err
    assert not (tmp_path / "o").exists()
