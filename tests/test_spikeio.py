"""Spike files: round trips, golden bytes, the real camera's layout, and clear errors."""
import numpy as np
import pytest

from spikegen.errors import InputError
from spikegen.spikeio import decode_dat, encode_dat, read_dat, read_npz, read_spikes, write_dat, write_npz


@pytest.mark.parametrize("shape", [(1, 1, 8), (3, 2, 8), (4, 8, 8), (2, 7, 16), (3, 250, 400), (2, 64, 40)])
def test_dat_round_trip(tmp_path, shape):
    rng = np.random.default_rng(sum(shape))
    s = (rng.random(shape) < 0.3).astype(np.uint8)
    write_dat(tmp_path / "a.dat", s)
    assert (tmp_path / "a.dat").stat().st_size == s.size // 8
    np.testing.assert_array_equal(read_dat(tmp_path / "a.dat", shape[1], shape[2]), s)


@pytest.mark.parametrize("shape", [(1, 1, 1), (3, 5, 7), (2, 250, 400)])
def test_npz_round_trip(tmp_path, shape):
    rng = np.random.default_rng(1)
    s = (rng.random(shape) < 0.5).astype(np.uint8)
    write_npz(tmp_path / "a.npz", s)
    np.testing.assert_array_equal(read_npz(tmp_path / "a.npz"), s)
    with np.load(tmp_path / "a.npz") as z:  # the documented layout
        np.testing.assert_array_equal(z["spikes"], np.packbits(s, axis=-1, bitorder="little"))
        assert tuple(z["shape"]) == shape


def test_dat_golden_bytes():
    # 2 frames of 2 rows x 8 columns. Rows are stored bottom to top, 8 pixels a byte, LSB first.
    s = np.zeros((2, 2, 8), np.uint8)
    s[0, 0, 0] = 1  # top row, first pixel  -> second byte, bit 0 -> 0x01
    s[0, 1, 7] = 1  # bottom row, last pixel -> first byte, bit 7 -> 0x80
    s[1, 0, 1] = s[1, 0, 2] = 1  # top row pixels 1, 2 -> second byte 0x06
    assert encode_dat(s) == bytes([0x80, 0x01, 0x00, 0x06])
    np.testing.assert_array_equal(decode_dat(bytes([0x80, 0x01, 0x00, 0x06]), 2, 8), s)


def test_truncated_dat_is_a_clear_error(tmp_path):
    p = tmp_path / "t.dat"
    p.write_bytes(b"\x00" * 101)
    with pytest.raises(InputError, match="t.dat.*not a whole number"):
        read_dat(p, 8, 8)
    with pytest.raises(InputError, match="holds 2 frames.*expected 3"):
        read_dat(_write(tmp_path / "u.dat", 2 * 8), 8, 8, frames=3)
    with pytest.raises(InputError, match="--size"):
        read_spikes(p)


def _write(p, n):
    p.write_bytes(b"\x00" * n)
    return p


def test_real_car_recording_is_upright(shared_data):
    """The .dat and the upright .npz show the same static background; read the right way up
    the two agree far better than with the .dat flipped."""
    dat = read_spikes(shared_data / "real" / "car_100kmh_250x400.dat", size=(400, 250))
    assert dat.shape == (200, 250, 400)
    assert abs(dat.mean() - 0.366) < 0.01
    with np.load(shared_data / "real" / "car_500frames_250x400.npz") as z:
        npz = np.moveaxis(z["arr_0"], -1, 0)
    a, b = dat.mean(0), npz.mean(0)
    upright = np.corrcoef(a[:60].ravel(), b[:60].ravel())[0, 1]  # top: trees, static
    flipped = np.corrcoef(a[::-1][:60].ravel(), b[:60].ravel())[0, 1]
    assert upright > 0.5 and upright > flipped + 0.3
    assert read_spikes(shared_data / "real" / "car_500frames_250x400.npz").shape == (500, 250, 400)
