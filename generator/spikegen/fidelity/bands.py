"""``spikegen diagnose`` a band of rows at a time: the measured stream and its models' simulations.

A stream of the whole recording is ``T x H x W`` bytes (2 GB for one second, 20000 frames, of a
250 x 400 camera), and the timing statistics of all its spikes take several times that. What the
diagnosis takes of a stream is per-pixel statistics (counts, intervals, windows) and sums over
pixels of counts per frame or window (population signals, quadrant counts). So the measured
stream is kept packed (:class:`Stream`, 8 pixels a byte) and unpacked a band of rows at a time,
and each model's simulation is made a block of bands at a time (:func:`simulated_bands`) and
reduced band by band. The simulator draws each block of sensor.CHUNK_ROWS rows from its own
random stream (sensor.simulate, ``rows``), so rows simulated alone are the same as those rows of
the whole simulation; each pixel's statistics are computed by the same functions from its own
spikes; sums over pixels are of whole numbers, exact in any order. What needs every pixel (the
held-out windows' population factor, row, column and mask means, the shared clock) is done
after a pass, on the per-pixel arrays. tests/test_diagnose.py checks that a diagnosis in bands
of 8 rows gives the same JSON, bit for bit, as one in a single band.
"""
from __future__ import annotations

import hashlib

import numpy as np

from ..sensor import CHUNK_ROWS, Sensor, simulate
from . import heldout, stats
from .records import SIM_SEED, SIM_THREADS, Context
from .unexplained import checks_from_parts, interval_fields

BAND_BYTES = 1 << 26  # bytes of one band of a dense stream [T, rows, W] (64 MiB) when no band is asked for


class Stream:
    """A measured stream ``[T, H, W]`` of 0/1, read a band of rows at a time: held dense
    (``uint8``) or packed, 8 pixels of a row a byte (``np.packbits(..., axis=-1,
    bitorder="little")``, as spikeio's ``.npz`` keeps it: an eighth of the memory)."""

    def __init__(self, shape: tuple, dense: np.ndarray | None = None, packed: np.ndarray | None = None):
        self.shape = tuple(int(v) for v in shape)
        self._dense, self._packed = dense, packed

    @classmethod
    def of(cls, spikes) -> "Stream":
        """``spikes`` itself if a :class:`Stream`, else the dense array ``[T, H, W]`` as one."""
        return spikes if isinstance(spikes, Stream) else cls(np.shape(spikes), dense=spikes)

    @property
    def frames(self) -> int:
        return self.shape[0]

    def rows(self, r0: int, r1: int, t0: int = 0, t1: int | None = None) -> np.ndarray:
        """``uint8 [t1 - t0, r1 - r0, W]``: frames ``t0:t1`` of rows ``r0:r1`` (a view of a dense stream)."""
        if self._dense is not None:
            return self._dense[t0:t1, r0:r1]
        return np.unpackbits(self._packed[t0:t1, r0:r1], axis=-1, bitorder="little", count=self.shape[2])

    def dense(self) -> np.ndarray:
        """The whole stream, ``uint8 [T, H, W]`` (unpacked if packed)."""
        return self._dense if self._dense is not None else self.rows(0, self.shape[1])


def band_rows(frames: int, height: int, width: int, rows: int | None = None) -> int:
    """Rows of a band: ``rows`` (a positive multiple of sensor.CHUNK_ROWS), or the most
    (a multiple of CHUNK_ROWS, at least CHUNK_ROWS) whose dense stream fits in BAND_BYTES."""
    if rows is None:
        rows = max(CHUNK_ROWS, (BAND_BYTES // max(frames * width, 1)) // CHUNK_ROWS * CHUNK_ROWS)
    elif rows <= 0 or rows % CHUNK_ROWS:
        raise ValueError(f"band rows must be a positive multiple of {CHUNK_ROWS}, got {rows}")
    return min(int(rows), height)


def bands(height: int, rows: int):
    """``(r0, r1)`` of each band of ``rows`` rows, top to bottom."""
    return [(r0, min(height, r0 + rows)) for r0 in range(0, height, rows)]


def simulate_rows(ctx: Context, sensor: Sensor, r0: int, r1: int) -> np.ndarray:
    """``[T, r1 - r0, W]``: rows ``r0:r1`` of ``sensor``'s stream of the diagnosis' reference
    radiance over the whole recording (seed SIM_SEED, so every model is compared on the same draws)."""
    return simulate(ctx.X, ctx.intensity, sensor, frames=ctx.frames, seed=SIM_SEED, threads=SIM_THREADS,
                    rows=(r0, r1))


SIM_BYTES = 1 << 28  # bytes of a block of simulated rows [T, rows, W] (256 MiB; its noise draws take twice that)


def simulated_bands(ctx: Context, sensor: Sensor, rows: int):
    """``(r0, r1, rows r0:r1 of the simulation)`` for each band of ``rows`` rows: simulated a
    block of several bands at a time (up to SIM_BYTES), since the simulator steps through the
    frames in Python and a block of few pixels would spend its time there."""
    for b0, b1, sim in simulated_blocks(ctx, sensor, rows):
        for r0, r1 in bands(b1 - b0, rows):
            yield b0 + r0, b0 + r1, sim[:, r0:r1]
        del sim


def simulated_blocks(ctx: Context, sensor: Sensor, rows: int):
    """``(b0, b1, rows b0:b1 of the simulation)`` for each block of :func:`simulated_bands`."""
    T, (H, W) = ctx.frames, ctx.shape
    block = max(rows, (SIM_BYTES // max(T * W, 1)) // rows * rows)
    for b0 in range(0, H, block):
        b1 = min(H, b0 + block)
        yield b0, b1, simulate_rows(ctx, sensor, b0, b1)


def simulation_key(sensor: Sensor, shape: tuple) -> str:
    """A digest of what a simulation of the diagnosis' reference depends on besides the context
    (radiance, intensity, frames and seed are the diagnosis' own): ``sensor``'s scalar parameters
    and its maps at ``shape``. Two sensors with the same key give the same stream."""
    R, d = sensor.maps(*shape)
    digest = hashlib.sha256(repr(sorted(sensor.parameters().items())).encode())
    for arr in (R, d):
        digest.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    return digest.hexdigest()


def model_pass(ctx: Context, sensor: Sensor, measures: bool = False, checks: bool = False) -> dict:
    """The held-out score of ``sensor`` (``"score"``: heldout.HeldOutScore, the module text of heldout,
    of its whole simulation), with ``measures`` also ``"measures"`` (stats.discrepancies of its held-out
    frames) and with ``checks`` ``"unexplained"`` (unexplained.unexplained), in one pass over
    bands of ``ctx.rows`` rows of its simulation. What an earlier pass of the same simulation
    (:func:`simulation_key`) computed is taken from ``ctx.passes`` instead of simulated again."""
    return simulation_pass(ctx, sensor, measures=measures, checks=checks)


def simulation_pass(ctx: Context, sensor: Sensor, score: bool = True, measures: bool = False, checks: bool = False,
                    window: dict | None = None) -> dict:
    """:func:`model_pass` (``"score"`` only with ``score``), and with ``window`` (``{"mask": [P]
    or None, "timing": as fit_window_pass}``) also ``"window"``: what :func:`fit_window_pass`
    returns of the simulation's fit window, from the same simulation. The score, measures and checks of each simulation are kept
    in ``ctx.passes`` (by :func:`simulation_key`): a pass simulates only if something asked for
    is not there, and computes only what is not there."""
    key = simulation_key(sensor, ctx.shape)
    done = ctx.passes.setdefault(key, {})
    want = {"score": score, "measures": measures, "unexplained": checks}
    todo = {k for k, v in want.items() if v and k not in done}
    if todo or window is not None:
        done.update(_simulate_and_reduce(ctx, sensor, "score" in todo, "measures" in todo,
                                         "unexplained" in todo, window))
    out = {k: done[k] for k, v in want.items() if v}
    if window is not None:
        out["window"] = done.pop("window")
    return out


def _simulate_and_reduce(ctx: Context, sensor: Sensor, score: bool, measures: bool, checks: bool,
                         window: dict | None) -> dict:
    """One simulation of ``sensor``, reduced band by band to what is asked for (see :func:`simulation_pass`)."""
    T, Tf, rows = ctx.frames, ctx.Tf, ctx.rows
    H, W = ctx.shape
    P = H * W
    static_ref = ctx.X.shape[0] == 1
    mask = ctx.static
    held = _HeldOutScore(ctx, sensor) if score else None
    acc = _Accumulators(P, T - Tf) if (measures or checks) else None
    fit = _FitWindow(ctx, window.get("mask"), timing=window.get("timing", "all")) if window is not None else None
    for b0, b1, block in simulated_blocks(ctx, sensor, rows):
        # the simulated intervals' moments of the whole block at once (a pass over its frames)
        moments = (stats.interval_moments_by_frame(block)
                   if held is not None and held.modulation is None else None)
        for a0, a1 in bands(b1 - b0, rows):
            r0, r1, sim = b0 + a0, b0 + a1, block[:, a0:a1]
            sl = slice(r0 * W, r1 * W)
            if held is not None or acc is not None:
                meas = ctx.spikes.rows(r0, r1, Tf)
                band = _Band(meas, sim)  # what both reductions take of the band, made once
                if moments is not None:
                    band.put("moments", tuple(m[a0 * W: a1 * W] for m in moments))
                if held is not None:
                    held.add(sl, band)
                if acc is not None:
                    acc.add(sl, band, mask[sl], static_ref, checks)
            if fit is not None:
                fit.add(r0, r1, sim[:Tf])
        del block
    out = {}
    if held is not None:
        out["score"] = held.finish()
    if measures:
        out["measures"] = acc.measures(ctx.X.mean(axis=0), H, W)
    if checks:
        out["unexplained"] = acc.unexplained(mask, H, W)
    if fit is not None:
        out["window"] = fit.finish()
    return out


class _Band:
    """A band's measured held-out frames ``meas [Th, rows, W]`` and simulation ``sim [T, rows, W]``,
    with what the held-out score and the accumulators both take of them (window counts, count
    variances, spike times, interval moments), each computed on first use (or :meth:`put` from
    its block) and then kept (the same arrays: none is changed in place by its users)."""

    def __init__(self, meas: np.ndarray, sim: np.ndarray):
        self.meas, self.sim = meas, sim
        self.held = sim[sim.shape[0] - meas.shape[0]:]  # the simulation's held-out frames
        self._memo = {}

    def _get(self, key, make):
        if key not in self._memo:
            self._memo[key] = make()
        return self._memo[key]

    def put(self, key, value) -> None:
        """Keep ``value`` as what ``key`` would compute (from a larger block: the same numbers)."""
        self._memo[key] = value

    def moments(self) -> tuple:
        """stats.interval_moments of the whole simulation."""
        return self._get("moments", lambda: stats.interval_moments(self.sim))

    def windows(self, which: str, w: int) -> np.ndarray:
        """heldout.window_counts of ``"meas"`` or ``"held"`` (the simulation's held-out frames)."""
        return self._get(("windows", which, w), lambda: heldout.window_counts(getattr(self, which), w))

    def count_variance(self, w: int, static_reference: bool, floor: float = heldout.VAR_FLOOR) -> np.ndarray:
        """heldout.count_variance of the whole simulation (no modulation), at least ``floor``."""
        raw = self._get(("cvar", w, static_reference),
                        lambda: heldout.count_variance(self.sim, w, static_reference, floor=0.0))
        return np.maximum(raw, floor)

    def times(self, which: str) -> tuple:
        """stats.spike_times of ``"meas"`` or ``"held"``."""
        return self._get(("times", which), lambda: stats.spike_times(getattr(self, which)))


class _HeldOutScore:
    """The held-out score (heldout's module text) of a model's whole simulation, band by band
    (:func:`simulation_pass`)."""

    def __init__(self, ctx: Context, sensor: Sensor):
        T, Tf = ctx.frames, ctx.Tf
        P = ctx.shape[0] * ctx.shape[1]
        self.ctx = ctx
        self.static_ref = ctx.X.shape[0] == 1
        self.modulation = heldout.model_modulation(sensor, ctx.X, ctx.intensity, T)
        self.lengths = heldout.window_lengths(T - Tf)
        self.interval_ll = np.zeros(P)
        self.count_ll = {w: np.zeros(P) for w in self.lengths}
        self.rate, self.cvar = np.zeros(P), {w: np.zeros(P) for w in self.lengths}
        self.pop = {w: 0.0 for w in self.lengths}
        # without modulation intervals and counts are pooled: the intervals on the judged pixels
        # (with a changing reference, those whose reference stays within heldout.QUASI_STILL of its
        # mean; the others: their own Gaussian), the counts' variances by rate, their means times
        # the population's factor (a static reference) or the reference's course (one that changes)
        self.pooled = self.modulation is None
        if self.pooled:
            R, d = sensor.maps(*ctx.shape)
            if not self.static_ref:
                self.course = heldout.ReferenceCourse(ctx.X, ctx.intensity, d, T)
            self.intervals = heldout.IntervalPool(P, T)
            self.judged_pooled = ctx.static & heldout.quasi_still(ctx.X)
            # the pools: pixels of like drive (charge per frame in thresholds, R (I X / 256 + d),
            # X's mean over the sub-frames, before the readout makes whole-frame intervals of it)
            self.drive = (R * (ctx.intensity / 256.0 * ctx.X.mean(axis=0) + d)).reshape(-1)

    def add(self, sl: slice, band: _Band) -> None:
        """The pixels ``sl``: the band's measured held-out frames and simulation."""
        meas, sim = band.meas, band.sim
        T, Th = sim.shape[0], meas.shape[0]
        band_mask = self.ctx.static[sl]
        if self.pooled:  # pooled over the judged pixels in finish()
            held_intervals = stats.intervals(meas, times=band.times("meas"))
            self.intervals.add(sl, stats.intervals(sim), band.moments(), held_intervals)
            if not self.static_ref:  # for the judged pixels that are not pooled
                self.interval_ll[sl] = heldout._interval_loglik(meas, band.moments(), held_intervals)
            self.rate[sl] = sim.reshape(T, -1).sum(axis=0, dtype=np.int64) / T
            band_mod = None
        else:
            band_mod = heldout.Modulation(self.modulation.phi, self.modulation.share[sl])
            self.interval_ll[sl] = heldout._clock_interval_loglik(meas, sim, band_mod)
        for w in self.lengths:
            if self.pooled and self.static_ref:
                s = band.windows("held", w)
                self.pop[w] = self.pop[w] + s[:, band_mask].sum(axis=1)
                self.cvar[w][sl] = band.count_variance(w, True, floor=0.0)
            elif self.pooled:
                self.cvar[w][sl] = heldout.count_variance(sim, w, False, self.course.part(sl), floor=0.0)
            else:
                self.count_ll[w][sl] = heldout._count_loglik(meas, sim, w, self.static_ref, band_mod)

    def finish(self) -> heldout.HeldOutScore:
        ctx, lengths = self.ctx, self.lengths
        W = ctx.shape[1]
        if self.pooled:
            pooled = self.intervals.finish(self.judged_pooled, -self.drive)
            self.interval_ll = np.where(self.judged_pooled, pooled, self.interval_ll)
            cvar = {w: heldout.pooled_count_variance(self.cvar[w], self.rate, ctx.static, w, ctx.frames)
                    for w in lengths}
            for r0, r1 in bands(ctx.shape[0], ctx.rows):
                sl = slice(r0 * W, r1 * W)
                for w in lengths:
                    c = heldout.window_counts(ctx.spikes.rows(r0, r1, ctx.Tf), w)
                    if self.static_ref:
                        factor = self.pop[w] / max(self.pop[w].mean(), 1e-12)
                    else:
                        factor = self.course.part(sl).window_factor(w, ctx.Tf, c.shape[0])
                    self.count_ll[w][sl] = heldout.count_loglik_given(c, factor, self.rate[sl], w, cvar[w][sl])
        per_pixel = self.interval_ll
        for w in lengths:
            per_pixel = per_pixel + self.count_ll[w] / len(lengths)
        return heldout.finish_score(per_pixel, ctx.static)


class _Accumulators:
    """What stats.discrepancies and unexplained.unexplained take from the two streams, band by band."""

    def __init__(self, P: int, Th: int):
        self.Th = Th
        self.fields = {}
        self.spectrum = {"m": np.zeros(Th, dtype=np.int64), "s": np.zeros(Th, dtype=np.int64)}
        self.hist = {k: np.zeros(Th + 1, dtype=np.int64) for k in ("m", "s", "m_mask", "s_mask")}
        self.frame = {"c": 0.0, "s": 0.0}
        self.lists = {k: [] for k in ("rm", "rs", "disp_d", "disp_s")}
        self.P = P

    def _put(self, name, sl, values):
        if name not in self.fields:
            self.fields[name] = np.zeros(self.P, dtype=np.asarray(values).dtype)
        self.fields[name][sl] = values

    def add(self, sl, band: _Band, mask, static_ref, checks):
        meas, sim_full, sim = band.meas, band.sim, band.held
        Th = self.Th
        pm = stats.pixel_stats(meas, times=band.times("meas"))
        ps = stats.pixel_stats(sim, times=band.times("held"))
        hm, hs = stats.isi_histogram(pm.isi_values, Th), stats.isi_histogram(ps.isi_values, Th)
        self.hist["m"] += hm
        self.hist["s"] += hs
        for k, p in (("m", pm), ("s", ps)):
            for f in ("rate", "n", "n_isi", "isi_var", "isi_mean", "ones"):
                self._put(f"{k}_{f}", sl, getattr(p, f))
        self._put("cm", sl, meas.reshape(Th, -1).mean(0))
        self._put("cs", sl, sim.reshape(Th, -1).mean(0))
        self.spectrum["m"] += meas.reshape(Th, -1).sum(axis=1, dtype=np.int64)
        self.spectrum["s"] += sim.reshape(Th, -1).sum(axis=1, dtype=np.int64)
        if not checks:
            return
        c = meas.reshape(Th, -1).sum(axis=0, dtype=np.int64).astype(np.float64)
        s = sim.reshape(Th, -1).sum(axis=0, dtype=np.int64).astype(np.float64)
        self._put("c", sl, c)
        self._put("s", sl, s)
        self._put("var", sl, 2.0 * heldout.count_variance(sim_full, Th, static_ref))
        self._put("var4", sl, band.count_variance(4, True))
        w4 = [band.windows(x, 4)[:, mask] for x in ("meas", "held")]
        self.frame["c"] = self.frame["c"] + w4[0].sum(axis=1)
        self.frame["s"] = self.frame["s"] + w4[1].sum(axis=1)
        self.frame["n"] = w4[0].shape[0]
        c16, s16 = (band.windows(x, 16)[:, mask] for x in ("meas", "held"))
        self.frame["n16"] = c16.shape[0]
        if c16.shape[0] >= 4:
            self.lists["disp_d"].append(c16.var(axis=0, ddof=1) - s16.var(axis=0, ddof=1))
            self.lists["disp_s"].append(s16.var(axis=0, ddof=1))
        for key, x, p in (("rm", "meas", pm), ("rs", "held", ps)):
            r = stats.serial_correlation(getattr(band, x), times=band.times(x))[mask & (p.isi_var >= 2.0) & (p.n_isi >= 8)]
            self.lists[key].append(r)
        keep = np.flatnonzero(mask)
        for key, x, p in (("m_mask", "meas", pm), ("s_mask", "held", ps)):
            pixels = stats.interval_pixels(getattr(band, x), times=band.times(x))
            self.hist[key] += stats.isi_histogram(p.isi_values[np.isin(pixels, keep)], Th)

    def _stats(self, k):
        f = self.fields
        return stats.PixelStats(self.Th, f[f"{k}_n"], None, None, f[f"{k}_rate"], f[f"{k}_isi_mean"],
                                f[f"{k}_isi_var"], None, None, None, f[f"{k}_ones"], f[f"{k}_n_isi"],
                                np.empty(int(self.hist[k].sum())), None)

    def measures(self, radiance_mean, H, W) -> dict:
        """stats.discrepancies of the held-out frames, from the accumulated parts."""
        return stats.discrepancy_measures(self._stats("m"), self._stats("s"), self.fields["cm"], self.fields["cs"],
                                          radiance_mean, H, W, self.hist["m"], self.hist["s"],
                                          self.spectrum["m"], self.spectrum["s"])

    def unexplained(self, mask, H, W) -> list:
        cat = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in self.lists.items()}
        cat["isi"] = interval_fields(self._stats("m"), self._stats("s"))
        return checks_from_parts(self.fields["c"], self.fields["s"], self.fields["var"], mask, H, W,
                                 self.frame, self.fields["var4"], cat, self.hist["m_mask"], self.hist["s_mask"])


# ---------------------------------------------------------------------- the measured stream's fit window
def pixel_stats(stream: Stream, rows: int, t0: int = 0, t1: int | None = None, clock=None) -> stats.PixelStats:
    """stats.pixel_stats of frames ``t0:t1`` of ``stream``, band by band (the same numbers), but
    without the pooled intervals (``isi_values`` is None: they are as many as the spikes)."""
    return join_stats([stats.pixel_stats(stream.rows(r0, r1, t0, t1), clock, values=False)
                       for r0, r1 in bands(stream.shape[1], rows)])


def fit_window_stats(stream: Stream, rows: int, Tf: int) -> tuple[stats.PixelStats, tuple]:
    """``(pixel_stats(stream, rows, 0, Tf), (window_rate of frames 0:Tf // 2, of Tf // 2:Tf))``,
    the same numbers, in one read of the fit window (the rates of the halves from its spike
    indices, stats.split_window_rates)."""
    parts, first, second = [], [], []
    for r0, r1 in bands(stream.shape[1], rows):
        band = stream.rows(r0, r1, 0, Tf)
        idx, starts, T = stats.pixel_major_spikes(band)
        parts.append(stats.frame_stats(idx, starts, T, extremes=True, values=False))
        a, b = stats.split_window_rates(idx, starts, T, Tf // 2)
        first.append(a)
        second.append(b)
    return join_stats(parts), (np.concatenate(first), np.concatenate(second))


def join_stats(parts: list) -> stats.PixelStats:
    """One stats.PixelStats of the pixels of ``parts`` (band by band, top to bottom); their
    ``isi_values`` joined (None if any is None)."""
    def cat(name):
        values = [getattr(p, name) for p in parts]
        return None if any(v is None for v in values) else np.concatenate(values)

    fields = ("n", "first", "last", "rate", "isi_mean", "isi_var", "span_var", "isi_min", "single", "ones", "n_isi",
              "isi_values", "diff_var")
    return stats.PixelStats(parts[0].frames, *(cat(f) for f in fields))


def window_rate(stream: Stream, rows: int, t0: int, t1: int) -> np.ndarray:
    """stats.window_rate of frames ``t0:t1`` of ``stream``, band by band."""
    return np.concatenate([stats.window_rate(stream.rows(r0, r1, t0, t1)) for r0, r1 in bands(stream.shape[1], rows)])


def population_signal(stream: Stream, mask: np.ndarray, rows: int, t0: int = 0, t1: int | None = None) -> np.ndarray:
    """stats.population_signal of frames ``t0:t1`` of ``stream`` over ``mask [P]``: whole numbers
    summed band by band (the same numbers)."""
    return population_signals(stream, [mask], rows, t0, t1)[0]


def population_signals(stream: Stream, masks: list, rows: int, t0: int = 0, t1: int | None = None) -> list:
    """:func:`population_signal` of each mask of ``masks`` (``[P]`` each), in one read of the stream."""
    W = stream.shape[2]
    masks = [np.asarray(m).reshape(-1) for m in masks]
    total = 0
    for r0, r1 in bands(stream.shape[1], rows):
        band = stream.rows(r0, r1, t0, t1)
        total = total + masked_frame_sums(band.reshape(band.shape[0], -1), [m[r0 * W: r1 * W] for m in masks])
    return [total[:, i].astype(np.float64) for i in range(len(masks))]


MATMUL_FRAMES = 2048  # frames converted to float32 at a time by masked_frame_sums


def masked_frame_sums(flat: np.ndarray, masks: list) -> np.ndarray:
    """``int64 [T, len(masks)]``: the spikes of each frame of ``flat [T, P]`` (0/1) summed over the
    pixels of each mask ``[P]``. A matrix product with the masks in float32, a block of frames at a
    time: every partial sum is a whole number below 2**24 (at most ``P`` ones), so exact in any
    order (BLAS threads included) and the same as summing the masked pixels one by one."""
    T, P = flat.shape
    if P >= 1 << 24:
        return np.stack([flat[:, m].sum(axis=1, dtype=np.int64) for m in masks], axis=1)
    onehot = np.stack(masks, axis=1).astype(np.float32)
    out = np.empty((T, len(masks)), dtype=np.float32)
    buf = np.empty((min(T, MATMUL_FRAMES), P), dtype=np.float32)
    for f0 in range(0, T, MATMUL_FRAMES):
        f1 = min(T, f0 + MATMUL_FRAMES)
        np.copyto(buf[: f1 - f0], flat[f0:f1])
        np.matmul(buf[: f1 - f0], onehot, out=out[f0:f1])
    return out.astype(np.int64)


def quadrant_counts(stream: Stream, mask: np.ndarray, rows: int, t1: int) -> np.ndarray:
    """stats.quadrant_counts of the first ``t1`` frames of ``stream`` over ``mask [P]``, band by band."""
    H = stream.shape[1]
    return sum(stats.quadrant_counts(stream.rows(r0, r1, 0, t1), mask, top=r0, height=H) for r0, r1 in bands(H, rows))


def fit_window_pass(ctx: Context, sensor: Sensor, rows: int, mask: np.ndarray | None = None,
                    clock_mask: np.ndarray | None = None, score: bool = False, timing: str | None = "all") -> dict:
    """Of ``sensor``'s simulation's fit window (its first ``Tf`` frames), band by band:
    ``"stats"`` (stats.pixel_stats, without ``isi_values``; with ``timing="variances"`` only the
    fields of stats.interval_variances, cheaper; with None no ``"stats"``), with ``mask [P]`` also
    ``"quadrants"`` (stats.quadrant_counts) and ``"signal"`` (stats.population_signal over
    ``mask``), with ``clock_mask`` all the stats measured on the population clock of those pixels
    instead (two passes). With ``score`` (``rows`` those of the context, no ``clock_mask``) the same
    simulation's held-out score is computed too and kept for :func:`model_pass`, which then need
    not simulate the sensor again (:func:`simulation_pass`)."""
    H, W = ctx.shape
    Tf = ctx.Tf
    if clock_mask is None and rows == ctx.rows:
        return simulation_pass(ctx, sensor, score=score, window={"mask": mask, "timing": timing})["window"]
    clock = None
    if clock_mask is not None:
        signal = 0
        for r0, r1, band in simulated_bands(ctx, sensor, rows):
            band = band[:Tf]
            signal = signal + band.reshape(Tf, -1)[:, clock_mask[r0 * W: r1 * W]].sum(axis=1, dtype=np.int64)
        clock = stats.clock_of(np.asarray(signal).astype(np.float64))
    fit = _FitWindow(ctx, mask, clock)
    for r0, r1, band in simulated_bands(ctx, sensor, rows):
        fit.add(r0, r1, band[:Tf])
    return fit.finish()


class _FitWindow:
    """What :func:`fit_window_pass` returns, band by band."""

    def __init__(self, ctx: Context, mask: np.ndarray | None, clock: np.ndarray | None = None,
                 timing: str | None = "all"):
        if timing not in ("all", "variances", None) or (clock is not None and timing != "all"):
            raise ValueError(f"timing must be 'all', 'variances' or None (with a clock 'all'), got {timing!r}")
        self.shape, self.mask, self.clock, self.timing = ctx.shape, mask, clock, timing
        self.parts, self.quads, self.signal = [], 0, 0

    def add(self, r0: int, r1: int, band: np.ndarray) -> None:
        """Rows ``r0:r1`` of the fit window, ``band [Tf, r1 - r0, W]``."""
        H, W = self.shape
        if self.timing == "all":
            self.parts.append(stats.pixel_stats(band, self.clock, values=False))
        elif self.timing == "variances":
            self.parts.append(stats.interval_variances(band))
        if self.mask is not None:
            self.quads = self.quads + stats.quadrant_counts(band, self.mask, top=r0, height=H)
            self.signal = self.signal + masked_frame_sums(band.reshape(band.shape[0], -1),
                                                          [self.mask[r0 * W: r1 * W]])[:, 0]

    def finish(self) -> dict:
        out = {"stats": join_stats(self.parts)} if self.timing is not None else {}
        if self.mask is not None:
            out["quadrants"], out["signal"] = self.quads, np.asarray(self.signal).astype(np.float64)
        return out


def motion_test(stream: Stream, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """heldout.motion_test of ``stream``, band by band: the shared clock from the population
    counts and the rates of all bands, then each pixel's tests in its band (the same numbers)."""
    H = stream.shape[1]
    spans = bands(H, rows)
    counts_ok = np.concatenate([heldout.segment_counts_ok(stream.rows(r0, r1)) for r0, r1 in spans])
    T, W = stream.shape[0], stream.shape[2]
    clock, clock_var = None, 0.0
    if T // stats.COMMON_WINDOW >= 4 and min(int(q[-1].sum()) for q in stats._quadrants(counts_ok, H, W)) >= 4:
        shared, se = stats.shared_variance_of(quadrant_counts(stream, counts_ok, rows, T))
        if counts_ok.any() and shared >= 5.0 * se and shared >= 0.01 ** 2:
            lam = np.concatenate([stream.rows(r0, r1).reshape(T, -1)[:, counts_ok[r0 * W: r1 * W]]
                                  .mean(axis=0, dtype=np.float64) for r0, r1 in spans])
            clock = stats.clock_of(population_signal(stream, counts_ok, rows))
            clock_var = heldout.clock_variance(lam)
    tests = {}
    for k in heldout.MOTION_SEGMENTS:
        parts = [heldout.dispersion_on_clock(stream.rows(r0, r1), k, clock, clock_var) for r0, r1 in spans]
        tests[k] = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    return heldout.motion_verdict(counts_ok, tests)
