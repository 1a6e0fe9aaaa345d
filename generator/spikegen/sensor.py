"""The spike-camera sensor model (shared/specs/sensor-model.md), pure NumPy, no I/O.

A view is ``K`` sub-frames of linear luminance ``X [K, H, W]`` turned into ``T`` readout
frames of spikes ``uint8 [T, H, W]``. The rate of a pixel in frame ``t`` is::

    lambda(x, y, t) = R(x, y) * ((I / 256) * X(x, y, t) + d(x, y))      # spikes per frame

with ``X(t)`` piecewise-linear between sub-frame centres ``(k + 0.5) T / K``. Each frame the
pixel integrates ``q = lambda`` (or, with photon shot noise, ``Poisson(N_e lambda) / N_e``),
fires when its accumulator reaches one threshold, subtracts it, and fires at most once a
frame (after a spike ``A = min(A, 1)``). With ``threshold_jitter = sigma`` it fires instead
when ``A`` reaches ``1 + eps``, ``eps ~ N(0, sigma^2)`` (clipped to +-JITTER_CLIP) drawn anew
after each spike, and still subtracts the nominal threshold 1: a spike's timing error does not
carry to the next (intervals vary by ``2 sigma^2 / lambda^2`` and consecutive ones correlate
by -1/2), unlike shot noise, whose timing errors accumulate.

Exactness. Charge is fixed-point: one threshold is ``ONE = 2**32`` units and every per-frame
charge is an integer number of units, defined by :class:`ChargeSchedule`. Integrating
integers is exact, so the fast path below (a wrapping ``uint32`` prefix sum whose carries are
the spikes) and a plain frame-by-frame loop give the same bits. The quantisation is 2**-32
of a threshold: far below any physical effect.

Randomness comes from a ``numpy.random.SeedSequence`` (see :mod:`spikegen.seeding`): child 0
draws the start phases, child ``1 + b`` the temporal noise of row block ``b`` (blocks of
``CHUNK_ROWS`` rows: the shot noise, then the threshold jitter's levels), so a stream never
depends on how the work is split.
"""
from __future__ import annotations

import dataclasses
import math
from functools import lru_cache
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .seeding import as_seed_sequence

ONE = 1 << 32  # one threshold, in fixed-point charge units
CHUNK_ROWS = 8  # rows whose temporal noise comes from one random stream (block b: child 1 + b)
FAST_CHUNK_PIXELS = 1 << 16  # pixels integrated together on the fast path (no effect on results)
MU_EXACT_POISSON = 30.0  # below this mean photo-electron count per frame, Poisson is drawn exactly
NORMAL_BITS = 16  # shot noise: a standard normal quantised to 2**16 equiprobable values
RESETS = ("subtract", "zero")
JITTER_CLIP = 0.5  # a firing level's relative offset is clipped to +-JITTER_CLIP thresholds
MAX_JITTER = 0.25  # the largest threshold_jitter accepted (the clip at 2 SD)
KINDS = ("if", "rsir")
# The sensor's scalar parameters, in the order sensor.json lists them (maps and map model apart).
SCALAR_FIELDS = ("name", "kind", "electrons", "reset", "refractory_frames", "threshold_jitter",
                 "flicker_period_frames", "flicker_depth", "crosstalk_fraction", "gamma", "lux_to_rate", "camera_seed")


@dataclass(frozen=True, eq=False)
class Sensor:
    """A sensor: per-pixel maps plus temporal and radiance effects.

    Every effect is off at its neutral value. Maps are ``[H, W]`` float arrays or ``None``
    (``R = 1``, ``d = 0``). ``map_model`` (optional) describes the maps statistically so that
    :meth:`sized` can draw maps of any size for the same camera (seeded by ``camera_seed``).
    """

    name: str = "ideal"
    responsivity: np.ndarray | None = None  # R [H, W], median 1
    dark_rate: np.ndarray | None = None  # d [H, W], spikes per frame at nominal response
    electrons: float = 0.0  # photo-electrons per threshold N_e; 0 = no shot noise
    reset: str = "subtract"  # "subtract" (residual kept) or "zero" (reset_to_zero effect)
    refractory_frames: int = 0
    # relative SD of the firing level, drawn anew after each spike; the reset subtracts the
    # nominal threshold, so the jitter does not accumulate (threshold_levels); 0 = none
    threshold_jitter: float = 0.0
    flicker_period_frames: float = 0.0
    flicker_depth: float = 0.0
    crosstalk_fraction: float = 0.0
    gamma: float = 1.0  # nonlinearity: X -> X ** gamma
    kind: str = "if"  # "if" (this model) or "rsir" (the paper's reference generator)
    lux_to_rate: float | None = None  # spikes per frame per lux at nominal response
    camera_seed: int = 0
    map_model: dict | None = None
    notes: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.reset not in RESETS:
            raise InputError(f"sensor {self.name!r}: reset must be one of {RESETS}, got {self.reset!r}")
        if self.kind not in KINDS:
            raise InputError(f"sensor {self.name!r}: kind must be one of {KINDS}, got {self.kind!r}")
        for label, value in (("electrons", self.electrons), ("refractory_frames", self.refractory_frames),
                             ("flicker_depth", self.flicker_depth), ("crosstalk_fraction", self.crosstalk_fraction),
                             ("flicker_period_frames", self.flicker_period_frames),
                             ("threshold_jitter", self.threshold_jitter)):
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"sensor {self.name!r}: {label} must be finite and >= 0, got {value}")
        if self.threshold_jitter > MAX_JITTER:
            raise InputError(f"sensor {self.name!r}: threshold_jitter must be <= {MAX_JITTER}, got {self.threshold_jitter}")
        if not (math.isfinite(self.gamma) and self.gamma > 0):
            raise InputError(f"sensor {self.name!r}: gamma must be > 0, got {self.gamma}")
        if self.flicker_depth > 0 and self.flicker_period_frames <= 0:
            raise InputError(f"sensor {self.name!r}: flicker needs flicker_period_frames > 0")
        for label, arr in (("responsivity", self.responsivity), ("dark_rate", self.dark_rate)):
            if arr is not None:
                a = np.asarray(arr)
                if a.ndim != 2 or not np.all(np.isfinite(a)) or a.min() < 0:
                    raise InputError(f"sensor {self.name!r}: {label} map must be a finite, non-negative [H, W] array")

    # ------------------------------------------------------------------ maps
    @property
    def shape(self) -> tuple[int, int] | None:
        for arr in (self.responsivity, self.dark_rate):
            if arr is not None:
                return tuple(np.shape(arr))
        return None

    def replace(self, **changes) -> "Sensor":
        return dataclasses.replace(self, **changes)

    def sized(self, height: int, width: int) -> "Sensor":
        """This camera's sensor at ``height x width``: its own maps if they fit, else maps drawn
        from ``map_model`` (seeded by ``camera_seed``); an error if neither."""
        if self.shape == (height, width) or (self.shape is None and self.map_model is None):
            return self
        if self.map_model is None:
            raise InputError(
                f"sensor {self.name!r}: its maps are {self.shape[1]}x{self.shape[0]}, the stream is "
                f"{width}x{height}, and it has no statistical map model to draw maps of another size"
            )
        from .fpn import draw_maps

        resp, dark = draw_maps(self.map_model, height, width, self.camera_seed, self.lux_to_rate, preset=self.name)
        return self.replace(responsivity=resp, dark_rate=dark)

    def maps(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, d) as float64 ``[H, W]`` arrays for a stream of this size."""
        s = self.sized(height, width)
        resp = np.ones((height, width)) if s.responsivity is None else np.asarray(s.responsivity, dtype=np.float64)
        dark = np.zeros((height, width)) if s.dark_rate is None else np.asarray(s.dark_rate, dtype=np.float64)
        return resp, dark

    @property
    def radiance_effects(self) -> bool:
        return self.gamma != 1.0 or self.crosstalk_fraction > 0 or self.flicker_depth > 0

    @property
    def simple_readout(self) -> bool:
        return self.reset == "subtract" and self.refractory_frames == 0 and self.threshold_jitter == 0

    def parameters(self) -> dict:
        """Scalar parameters (no maps), as written to ``sensor.json``: :data:`SCALAR_FIELDS` in order."""
        return {k: getattr(self, k) for k in SCALAR_FIELDS}


# ---------------------------------------------------------------------- time: sub-frames -> frames
def frame_segments(subframes: int, frames: int):
    """Split frames ``0..T-1`` into runs where the radiance is constant or linear.

    Returns a list of ``(a, b, k, linear)``: frames ``a <= t < b`` lie between centres
    ``c_k`` and ``c_{k+1}`` (``linear``) or are held at sub-frame ``k`` (before the first
    centre, after the last one). Centres are ``c_k = (k + 0.5) T / K``.
    """
    K, T = subframes, frames
    centres = [(k + 0.5) * T / K for k in range(K)]
    bounds = [min(T, max(0, math.ceil(c))) for c in centres]
    segs = []
    if bounds[0] > 0:
        segs.append((0, bounds[0], 0, False))
    for k in range(K - 1):
        if bounds[k + 1] > bounds[k]:
            segs.append((bounds[k], bounds[k + 1], k, True))
    if bounds[-1] < T:
        segs.append((bounds[-1], T, K - 1, False))
    return segs


def interpolation_weights(subframes: int, frames: int) -> np.ndarray:
    """``W [T, K]`` with ``X(t) = W @ X_k``: piecewise-linear between sub-frame centres."""
    K, T = subframes, frames
    w = np.zeros((T, K))
    step = T / K
    for a, b, k, linear in frame_segments(K, T):
        if not linear:
            w[a:b, k] = 1.0
            continue
        f = (np.arange(a, b) - (k + 0.5) * step) / step
        w[a:b, k] = 1.0 - f
        w[a:b, k + 1] = f
    return w


class ChargeSchedule:
    """Fixed-point charge per frame of P pixels whose rate is piecewise-linear in time.

    ``lam [K, P]`` are the rates (spikes per frame, >= 0) at the sub-frame centres. In each
    run of frames ``a <= t < b`` the charge is ``q_t = U + V (t - a)`` (integers, units of
    ``ONE``): ``U`` is the interpolated charge at frame ``a`` (exact when the run starts on a
    centre; otherwise rounded towards the run's start value), ``V`` the slope rounded towards
    zero, so ``q_t`` never leaves the range of its two end values and never differs from
    exact interpolation by more than ``b - a`` units. Rates are clipped to ``[0, 2]``: above
    one spike a frame the pixel saturates either way.
    """

    def __init__(self, lam: np.ndarray, frames: int):
        lam = np.asarray(lam, dtype=np.float64)
        self._build(lam * float(ONE), frames)

    @classmethod
    def from_radiance(cls, x: np.ndarray, intensity: float, resp: np.ndarray, dark: np.ndarray,
                      frames: int) -> "ChargeSchedule":
        """Schedule of ``lambda = R ((I / 256) X + d)`` for sub-frames ``x [K, P]`` and maps
        ``resp``, ``dark`` ``[P]``: the definition used by every path of the simulator."""
        gain = resp * (float(intensity) / 256.0 * ONE)  # [P], charge units per unit radiance
        offset = resp * dark * float(ONE)  # [P]
        scaled = np.multiply(x, gain, dtype=np.float64)
        scaled += offset
        self = cls.__new__(cls)
        self._build(scaled, frames)
        return self

    def _build(self, scaled: np.ndarray, frames: int) -> None:
        K, P = scaled.shape
        self.frames, self.pixels, self.subframes = frames, P, K
        np.minimum(scaled, 2.0 * ONE, out=scaled)
        self.levels = np.rint(scaled, out=scaled).astype(np.int64)  # [K, P]
        self.saturating = self.levels.max(axis=0) >= ONE  # [P]
        self.step = frames / K
        self.runs = frame_segments(K, frames)
        self.starts = np.array([r[0] for r in self.runs], dtype=np.int64)
        self.stops = np.array([r[1] for r in self.runs], dtype=np.int64)
        if K > 1:
            slope = np.diff(self.levels, axis=0).astype(np.float64)
            slope /= self.step
            self.slopes = np.trunc(slope, out=slope).astype(np.int64)  # [K-1, P]
        else:
            self.slopes = np.zeros((0, P), dtype=np.int64)

    def run_rows(self, i: int, cols=None) -> tuple[np.ndarray, np.ndarray | None]:
        """``(U, V)`` of run ``i`` as int64 ``[P]`` (V is None for a held run)."""
        a, b, k, linear = self.runs[i]
        lv = self.levels if cols is None else self.levels[:, cols]
        if not linear:
            return lv[k], None
        V = self.slopes[k] if cols is None else self.slopes[k, cols]
        offset = (a - (k + 0.5) * self.step) / self.step  # fraction of the run before frame a
        if offset == 0:
            return lv[k], V
        delta = (lv[k + 1] - lv[k]).astype(np.float64)
        exact = lv[k] + delta * offset
        return np.where(delta >= 0, np.floor(exact), np.ceil(exact)).astype(np.int64), V

    @property
    def U(self) -> np.ndarray:
        return np.stack([self.run_rows(i)[0] for i in range(len(self.runs))])

    @property
    def V(self) -> np.ndarray:
        zero = np.zeros(self.pixels, dtype=np.int64)
        return np.stack([v if v is not None else zero for v in (self.run_rows(i)[1] for i in range(len(self.runs)))])

    def min_max(self) -> tuple[np.ndarray, np.ndarray]:
        """Smallest and largest charge of each pixel over all frames, ``int64 [P]`` each."""
        U, V = self.U, self.V
        last = U + V * (self.stops - self.starts - 1)[:, None]
        return np.minimum(U, last).min(axis=0), np.maximum(U, last).max(axis=0)

    def frame(self, t: int) -> np.ndarray:
        """Charge of frame ``t`` for every pixel, ``int64 [P]``."""
        i = int(np.searchsorted(self.stops, t, side="right"))
        U, V = self.run_rows(i)
        return U if V is None else U + V * (t - self.starts[i])

    def dense_int64(self, cols=None) -> np.ndarray:
        """All frames, ``int64 [T, P]`` (or only columns ``cols``)."""
        n = self.pixels if cols is None else len(cols)
        out = np.empty((self.frames, n), dtype=np.int64)
        for i, (a, b) in enumerate(zip(self.starts, self.stops)):
            U, V = self.run_rows(i, cols)
            if V is None:
                out[a:b] = U
                continue
            np.multiply(np.arange(b - a, dtype=np.int64)[:, None], V, out=out[a:b])
            out[a:b] += U
        return out


# ---------------------------------------------------------------------- readout
def carry_readout(q: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """Integrate-and-fire with subtractive reset, no saturation: spikes are carries.

    ``q uint32 [T, P]`` (each < one threshold), ``phase uint32 [P]`` the start charge.
    The accumulator's fraction is the wrapping prefix sum ``C_t = phase + sum q``; frame
    ``t`` fires exactly when the addition of ``q_t`` wrapped, i.e. when ``C_t < q_t``.
    Returns ``bool [T, P]``.
    """
    acc = q.copy()
    acc[0] += phase
    np.cumsum(acc, axis=0, dtype=np.uint32, out=acc)
    return np.less(acc, q)


def loop_readout(q: np.ndarray, phase: np.ndarray, reset: str = "subtract", refractory_frames: int = 0,
                 jitter: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """Frame-by-frame integrate-and-fire, any reset and refractory period, any threshold jitter.

    ``q int64 [T, P]`` in units of ``ONE`` (may exceed one threshold), ``phase [P]``.
    Fires when ``A >= ONE + L`` (``L`` the pixel's firing level offset: 0 without jitter);
    subtractive reset removes the nominal threshold ``ONE`` from a pixel that fired and keeps
    the residual, clamped to ``A <= ONE`` (one spike a frame at most); ``reset="zero"`` discards it. During
    ``refractory_frames`` frames after a spike the pixel neither integrates nor fires.
    ``jitter > 0`` (needs ``rng``): ``L`` is drawn by :func:`threshold_levels` for every pixel
    at the start and again for each pixel that fires, right after its spike (in pixel order,
    frame by frame). Returns ``bool [T, P]``.
    """
    T, P = q.shape
    acc = phase.astype(np.int64)
    out = np.zeros((T, P), dtype=bool)
    wait = np.zeros(P, dtype=np.int64) if refractory_frames else None
    level = threshold_levels(rng, jitter, P) + ONE if jitter > 0 else ONE
    for t in range(T):
        if wait is None:
            acc += q[t]
            fire = acc >= level
        else:
            active = wait == 0
            acc += np.where(active, q[t], 0)
            fire = active & (acc >= level)
            np.subtract(wait, 1, out=wait, where=~active)
            wait[fire] = refractory_frames
        if reset == "zero":
            acc[fire] = 0
        else:
            acc -= fire * ONE
            np.minimum(acc, ONE, out=acc, where=fire)  # only a pixel that fired can exceed ONE here
        if jitter > 0:
            fired = np.flatnonzero(fire)
            if fired.size:
                level[fired] = threshold_levels(rng, jitter, fired.size) + ONE
        out[t] = fire
    return out


def threshold_levels(rng: np.random.Generator, jitter: float, n: int) -> np.ndarray:
    """``n`` firing-level offsets, ``int64`` units of ``ONE``: ``N(0, jitter^2)`` thresholds
    clipped to ``+-JITTER_CLIP``, drawn from ``rng`` (float64 normals, then rounded)."""
    eps = np.clip(rng.normal(0.0, jitter, n), -JITTER_CLIP, JITTER_CLIP)
    return np.rint(eps * ONE).astype(np.int64)


# ---------------------------------------------------------------------- the simulator
def start_phase(seed, height: int, width: int) -> np.ndarray:
    """Start charge ``A ~ U(0, 1)`` of every pixel, ``uint32 [H, W]`` in units of ``ONE``."""
    rng = np.random.Generator(np.random.PCG64(_child(as_seed_sequence(seed), 0)))
    return rng.integers(0, ONE, size=(height, width), dtype=np.uint64).astype(np.uint32)


def simulate(radiance, intensity: float, sensor: Sensor | None = None, frames: int = 256, seed=0,
             phase: np.ndarray | None = None, progress=None, threads: int = 1,
             rows: tuple[int, int] | None = None) -> np.ndarray:
    """Spike stream of one view.

    radiance: linear luminance, ``[K, H, W]`` sub-frames or ``[H, W]`` (static, K = 1).
    intensity: I, spikes per 256 frames of a nominal pixel at ``X = 1``.
    sensor: the sensor (default ``ideal``); its maps are drawn or checked for ``H x W``.
    frames: T. seed: int or SeedSequence (see :mod:`spikegen.seeding`).
    phase: optional start charge ``uint32 [H, W]`` (overrides the seeded one).
    progress: optional callable(rows_done, rows_total).
    threads: row blocks integrated in parallel threads (the result does not depend on it).
    rows: ``(r0, r1)``, only those rows (``r0`` a multiple of CHUNK_ROWS, ``r1`` one or ``H``):
    each block of CHUNK_ROWS rows draws its noise from its own stream, so they are the same
    rows as in the whole stream.
    Returns ``uint8 [T, H, W]`` of 0/1 (``[T, r1 - r0, W]`` with ``rows``).
    """
    x = _checked_radiance(radiance, intensity, frames)
    K, H, W = x.shape
    sensor = (sensor or Sensor()).sized(H, W)
    resp, dark = sensor.maps(H, W)
    ss = as_seed_sequence(seed)
    phase = start_phase(ss, H, W) if phase is None else np.asarray(phase, dtype=np.uint32)
    if phase.shape != (H, W):
        raise InputError(f"phase must be [{H}, {W}], got {phase.shape}")
    top, bottom = (0, H) if rows is None else (int(rows[0]), int(rows[1]))
    if not (0 <= top < bottom <= H and top % CHUNK_ROWS == 0 and (bottom % CHUNK_ROWS == 0 or bottom == H)):
        raise InputError(f"rows must be (r0, r1) within 0..{H}, at multiples of {CHUNK_ROWS}, got {rows}")
    out = np.empty((frames, bottom - top, W), dtype=np.uint8)
    fast = sensor.kind == "if" and not sensor.radiance_effects and sensor.simple_readout
    step = _rows_per_chunk(bottom - top, W, fast, max(1, int(threads)))  # the rows asked for: one chunk a thread
    run = _fast_rows if fast else _dense_rows

    def chunk(r0):
        r1 = min(bottom, r0 + step)
        rngs = [np.random.Generator(np.random.PCG64(_child(ss, 1 + b)))
                for b in range(r0 // CHUNK_ROWS, (r1 + CHUNK_ROWS - 1) // CHUNK_ROWS)]
        run(x, r0, r1, float(intensity), sensor, resp, dark, phase, frames, rngs,
            out.reshape(frames, -1)[:, (r0 - top) * W: (r1 - top) * W])
        return r1

    _run_chunks(chunk, range(top, bottom, step), max(1, int(threads)), progress, H)
    return out


def _checked_radiance(radiance, intensity: float, frames: int) -> np.ndarray:
    """``radiance`` as ``[K, H, W]``; an :class:`InputError` for a bad shape, value, intensity or T."""
    x = np.asarray(radiance)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[0] < 1 or 0 in x.shape:
        raise InputError(f"radiance must be [K, H, W] or [H, W], got shape {np.shape(radiance)}")
    if not np.all(np.isfinite(x)):
        raise InputError("radiance has NaN or infinite values")
    if x.min() < 0:
        raise InputError(f"radiance has negative values (min {float(x.min()):.4g})")
    if not (math.isfinite(intensity) and intensity > 0):
        raise InputError(f"intensity must be a positive number, got {intensity}")
    if int(frames) != frames or frames < 1:
        raise InputError(f"frames must be a positive integer, got {frames}")
    return x


def _rows_per_chunk(H: int, W: int, fast: bool, threads: int) -> int:
    """Rows integrated together: a multiple of CHUNK_ROWS (no effect on the result)."""
    step = max(CHUNK_ROWS, (FAST_CHUNK_PIXELS // W) // CHUNK_ROWS * CHUNK_ROWS) if fast else CHUNK_ROWS
    if threads > 1:  # at least one chunk per thread
        step = min(step, max(CHUNK_ROWS, -(-H // (threads * CHUNK_ROWS)) * CHUNK_ROWS))
    return step


def _run_chunks(chunk, starts, threads: int, progress, H: int) -> None:
    """``chunk(r0)`` for every start, in ``threads`` threads (NumPy releases the GIL inside its
    loops; chunks write disjoint outputs); ``progress(rows_done, H)`` after each."""
    if threads == 1:
        done = map(chunk, starts)
    else:
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(max_workers=threads)
        done = pool.map(chunk, starts)
    try:
        for r1 in done:
            if progress is not None:
                progress(r1, H)
    finally:
        if threads > 1:
            pool.shutdown()


def _child(ss: np.random.SeedSequence, i: int) -> np.random.SeedSequence:
    # An explicit child (not ss.spawn, which changes ss and so the next call's streams).
    return np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (i,), pool_size=ss.pool_size)


def _block_columns(r0, r1, W):
    """Column slices (within rows r0..r1 flattened) of the noise blocks of CHUNK_ROWS rows."""
    return [slice((b - r0) * W, (min(r1, b + CHUNK_ROWS) - r0) * W) for b in range(r0, r1, CHUNK_ROWS)]


def _fast_rows(x, r0, r1, intensity, sensor, resp, dark, phase, T, rngs, out):
    """Rates piecewise-linear in time, subtractive reset: integrate all frames in one pass."""
    K, H, W = x.shape
    P = (r1 - r0) * W
    R, d, a0 = resp[r0:r1].reshape(P), dark[r0:r1].reshape(P), phase[r0:r1].reshape(P)
    sched = ChargeSchedule.from_radiance(x[:, r0:r1].reshape(K, P), intensity, R, d, T)
    if sensor.electrons == 0:
        fused_carry(sched, a0, out)
        slow = np.flatnonzero(sched.saturating)
        if slow.size:
            out[:, slow] = loop_readout(sched.dense_int64(slow), a0[slow])
        return
    zs = normal_table(sensor.electrons)
    u = np.concatenate([rng.integers(0, 1 << NORMAL_BITS, size=(T, sl.stop - sl.start), dtype=np.uint16)
                        for rng, sl in zip(rngs, _block_columns(r0, r1, W))], axis=1)
    lo, hi = sched.min_max()
    exact = lo * (sensor.electrons / ONE) < MU_EXACT_POISSON
    maybe_sat = hi.astype(np.float64) + np.sqrt(hi) * float(zs.max()) >= ONE - 512
    fused_carry(sched, a0, out, noise=(zs, u))
    for rng, sl in zip(rngs, _block_columns(r0, r1, W)):
        cols = np.flatnonzero(exact[sl] | maybe_sat[sl]) + sl.start
        if cols.size:
            charge = _noisy(sched.dense_int64(cols), zs, u[:, cols], exact[cols], sensor.electrons, rng)
            out[:, cols] = _readout_dense(charge, a0[cols], sensor)


def _dense_rows(x, r0, r1, intensity, sensor, resp, dark, phase, T, rngs, out):
    """Any effect: per-frame radiance, then charge, noise and readout (one noise block)."""
    K, H, W = x.shape
    P = (r1 - r0) * W
    R, d, a0 = resp[r0:r1].reshape(P), dark[r0:r1].reshape(P), phase[r0:r1].reshape(P)
    rng = rngs[0]
    if sensor.kind == "if" and not sensor.radiance_effects:
        charge = ChargeSchedule.from_radiance(x[:, r0:r1].reshape(K, P), intensity, R, d, T).dense_int64()
    else:
        xt = _frame_radiance(x, r0, r1, T, sensor)  # [T, P] after radiance effects
        if sensor.kind == "rsir":
            charge = _quantise(rsir_charge(xt, intensity, R, d, rng))
        else:
            charge = _quantise(R * (intensity / 256.0 * xt + d))
    if sensor.electrons > 0:
        charge = shot_noise(charge, sensor.electrons, rng)
    out[:] = _readout_dense(charge, a0, sensor, rng)  # the jitter's levels: from rng after the charge's draws


def fused_carry(sched: "ChargeSchedule", phase: np.ndarray, out: np.ndarray, noise=None) -> None:
    """Integrate-and-fire, subtractive reset, in one pass over frames: ``out [T, P]`` (uint8
    or bool) receives the carries of a wrapping uint32 accumulator (see :func:`carry_readout`).

    The charge of each frame is made incrementally (``q += V`` within a run). With
    ``noise = (zs, u)`` each frame's charge gets shot noise ``sqrt(q) * zs[u[t]]``
    (:func:`noisy_charge_f32`). Pixels that may saturate (or need exact Poisson noise) are
    wrong here and must be redone by the caller.
    """
    acc = phase.astype(np.uint32)  # a copy
    q = np.empty(sched.pixels, dtype=np.uint32)
    if noise is not None:
        zs, u = noise
        qf = np.empty(sched.pixels, dtype=np.float32)
        z = np.empty(sched.pixels, dtype=np.float32)
        qn = np.empty(sched.pixels, dtype=np.uint32)
    for i, (a, b) in enumerate(zip(sched.starts, sched.stops)):
        U, V = sched.run_rows(i)
        q[:] = U  # C cast: wraps modulo 2**32, exact for non-saturating pixels
        V = None if V is None or not V.any() else V.astype(np.uint32)
        for t in range(a, b):
            if V is not None and t > a:
                q += V
            if noise is None:
                acc += q
                np.less(acc, q, out=out[t])
                continue
            np.take(zs, u[t], out=z)
            qf[:] = q
            noisy_charge_f32(qf, z, out=qf)
            with np.errstate(invalid="ignore"):  # only in pixels the caller redoes
                qn[:] = qf
            acc += qn
            np.less(acc, qn, out=out[t])


def noisy_charge_f32(q: np.ndarray, z: np.ndarray, out=None) -> np.ndarray:
    """``q + sqrt(q) * z`` in float32: ``q`` the mean charge (units of ONE, as float32),
    ``z`` standard normals already scaled by ``sqrt(ONE / N_e)``. One definition, used by
    the fast and the dense path so that both give the same bits."""
    s = np.sqrt(q)
    s *= z
    return np.add(q, s, out=out)


@lru_cache(maxsize=8)
def normal_table(electrons: float) -> np.ndarray:
    """``float32 [2**16]``: ``Phi^-1((i + 0.5) / 2**16) * sqrt(ONE / N_e)``."""
    p = (np.arange(1 << NORMAL_BITS, dtype=np.float64) + 0.5) / (1 << NORMAL_BITS)
    return (_norm_ppf(p) * math.sqrt(ONE / electrons)).astype(np.float32)


def _norm_ppf(p: np.ndarray) -> np.ndarray:
    """Inverse standard normal CDF (Acklam's rational approximation, relative error < 1.2e-9)."""
    a = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02, 1.383577518672690e+02,
         -3.066479806614716e+01, 2.506628277459239e+00)
    b = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02, 6.680131188771972e+01,
         -1.328068155288572e+01)
    c = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00, -2.549732539343734e+00,
         4.374664141464968e+00, 2.938163982698783e+00)
    dd = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00, 3.754408661907416e+00)
    p = np.asarray(p, dtype=np.float64)
    out = np.empty_like(p)
    lo, hi = p < 0.02425, p > 1 - 0.02425
    mid = ~(lo | hi)
    q = p[mid] - 0.5
    r = q * q
    out[mid] = (((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5]) * q / \
               (((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1)
    for mask, sign in ((lo, 1.0), (hi, -1.0)):
        qq = np.sqrt(-2 * np.log(np.where(sign > 0, p[mask], 1 - p[mask])))
        out[mask] = sign * (((((c[0] * qq + c[1]) * qq + c[2]) * qq + c[3]) * qq + c[4]) * qq + c[5]) / \
                    ((((dd[0] * qq + dd[1]) * qq + dd[2]) * qq + dd[3]) * qq + 1)
    return out


def _noisy(charge, zs, u, exact_cols, electrons, rng) -> np.ndarray:
    """Shot noise on ``charge int64 [T, n]`` with the 16-bit normals ``u [T, n]`` already drawn
    for these pixels; columns flagged ``exact_cols`` get exact Poisson draws from ``rng``."""
    qf = charge.astype(np.float32)
    noisy = np.maximum(noisy_charge_f32(qf, zs[u]), 0.0).astype(np.int64)
    if exact_cols.any():
        mu = charge[:, exact_cols].astype(np.float64) * (electrons / ONE)
        noisy[:, exact_cols] = np.rint(rng.poisson(mu) * (ONE / electrons)).astype(np.int64)
    return np.minimum(noisy, 2 * ONE)


def _readout_dense(charge: np.ndarray, a0, sensor: Sensor, rng: np.random.Generator | None = None) -> np.ndarray:
    if not sensor.simple_readout:
        return loop_readout(charge, a0, sensor.reset, int(sensor.refractory_frames), sensor.threshold_jitter, rng)
    sat = (charge >= ONE).any(axis=0)
    if not sat.any():
        return carry_readout(charge.astype(np.uint32), a0)
    out = np.empty(charge.shape, dtype=bool)
    ok = ~sat
    if ok.any():
        out[:, ok] = carry_readout(charge[:, ok].astype(np.uint32), a0[ok])
    out[:, sat] = loop_readout(charge[:, sat], a0[sat])
    return out


def _quantise(q: np.ndarray) -> np.ndarray:
    """Charge in thresholds (float) -> int64 units of ``ONE`` (clipped to [0, 2])."""
    return np.rint(np.minimum(np.maximum(q, 0.0), 2.0) * ONE).astype(np.int64)


def _frame_radiance(x, r0, r1, T, sensor: Sensor) -> np.ndarray:
    """``X(t)`` of rows r0..r1 for every frame, ``[T, P]`` float64, radiance effects applied
    in the order of sensor-model.md: nonlinearity, crosstalk, flicker."""
    K, H, W = x.shape
    halo = 1 if sensor.crosstalk_fraction > 0 else 0
    h0, h1 = max(0, r0 - halo), min(H, r1 + halo)
    wts = interpolation_weights(K, T)
    xt = (wts @ x[:, h0:h1].reshape(K, -1).astype(np.float64)).reshape(T, h1 - h0, W)
    if sensor.gamma != 1.0:
        np.power(xt, sensor.gamma, out=xt)
    if sensor.crosstalk_fraction > 0:
        xt = crosstalk(xt, sensor.crosstalk_fraction)
        xt = xt[:, r0 - h0: r0 - h0 + (r1 - r0)]
    if sensor.flicker_depth > 0:
        t = np.arange(T, dtype=np.float64)
        xt = xt * (1.0 + sensor.flicker_depth * np.sin(2 * np.pi * t / sensor.flicker_period_frames))[:, None, None]
    return np.ascontiguousarray(xt).reshape(T, -1)


def neighbour_mean(x: np.ndarray) -> np.ndarray:
    """Mean of the 4 neighbours of every pixel of ``[..., H, W]``; neighbours outside the
    image are left out of the mean, and a pixel with none keeps its own value."""
    total = np.zeros(x.shape, dtype=np.float64)
    count = np.zeros(x.shape[-2:])
    total[..., 1:, :] += x[..., :-1, :]
    count[1:, :] += 1
    total[..., :-1, :] += x[..., 1:, :]
    count[:-1, :] += 1
    total[..., :, 1:] += x[..., :, :-1]
    count[:, 1:] += 1
    total[..., :, :-1] += x[..., :, 1:]
    count[:, :-1] += 1
    return np.where(count == 0, x, total / np.maximum(count, 1))


def crosstalk(xt: np.ndarray, fraction: float) -> np.ndarray:
    """``X' = (1 - c) X + c * mean of the 4 neighbours`` on ``[..., H, W]``.

    Neighbours outside the array are left out of the mean. On a block of rows with a one-row
    halo the halo rows' own outputs are therefore not valid: the caller drops them.
    """
    return (1.0 - fraction) * xt + fraction * neighbour_mean(xt)


def shot_noise(charge: np.ndarray, electrons: float, rng: np.random.Generator) -> np.ndarray:
    """Photon shot noise on fixed-point charge ``int64 [T, P]``: ``q = Poisson(N_e q) / N_e``.

    A pixel whose mean photo-electron count per frame ``N_e q`` falls below
    ``MU_EXACT_POISSON`` in any frame gets exact Poisson draws. The others get the Poisson
    law's normal limit ``N(mu, mu)``, with the normal quantised to 2**16 equiprobable values
    (``|z| < 4.4``; skewness of the exact law ``mu**-0.5 < 0.19``; a spike sums ``N_e``
    electrons over several frames, so spike timing cannot tell them apart). Draw order from
    ``rng``: the 16-bit normals of all pixels ``[T, P]``, then the Poisson draws.
    """
    u = rng.integers(0, 1 << NORMAL_BITS, size=charge.shape, dtype=np.uint16)
    exact = charge.min(axis=0) * (electrons / ONE) < MU_EXACT_POISSON
    return _noisy(charge, normal_table(electrons), u, exact, electrons, rng)


def rsir_charge(xt: np.ndarray, intensity: float, R: np.ndarray, delta: np.ndarray, rng) -> np.ndarray:
    """Charge per frame of the paper's reference generator (Zhu et al., ACM MM 2023).

    Per frame: gray level ``v ~ Poisson(I X 255/256)``; interval ``D = 255 / v - 1``;
    nonuniformity and dark current ``D' = D / (R + D delta)``; quantisation noise
    ``D'' = D' + U(0, 1)``; charge ``q = 1 / (D'' + 1)``. ``v = 0`` gives ``D = inf`` and
    ``D' = 1 / delta`` (a dark pixel gets about ``delta`` a frame). ``D''`` is kept >= 0.
    """
    v = rng.poisson(xt * (intensity * 255.0 / 256.0)).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        D = np.where(v > 0, 255.0 / np.maximum(v, 1.0) - 1.0, np.inf)
        Dp = np.where(np.isfinite(D), D / (R + D * delta), np.where(delta > 0, 1.0 / np.maximum(delta, 1e-300), np.inf))
    Dpp = np.maximum(Dp + rng.random(xt.shape), 0.0)
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(Dpp), 1.0 / (Dpp + 1.0), 0.0)


def rsir_mean_charge(mean_gray: float, R: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Mean of :func:`rsir_charge` per frame (= spikes per frame) at a constant mean gray level
    ``m = I X 255/256``, over the Poisson gray level ``v`` and the uniform noise ``U``.

    The mean over ``U`` of ``1 / (D' + U + 1)`` is ``ln((D' + 2) / (D' + 1))``; ``v = 0`` gives
    ``D' = 1 / delta`` (charge 0 where ``delta = 0``). The Poisson sum runs to ``m + 6 sqrt(m) + 6``.
    The trainer's differentiable mirror is ``spikenerf.neuron.rsir_rate`` (tested to agree).
    """
    R, delta = np.broadcast_arrays(np.asarray(R, np.float64), np.asarray(delta, np.float64))
    m = float(mean_gray)
    if m < 0:
        raise ValueError("the mean gray level must be >= 0")
    v = np.arange(0, int(m + 6.0 * m ** 0.5 + 6) + 1, dtype=np.float64)
    log_fact = np.concatenate([[0.0], np.cumsum(np.log(v[1:]))])
    pmf = np.exp(v * np.log(m) - m - log_fact) if m > 0 else (v == 0).astype(np.float64)
    D = np.maximum(255.0 / np.maximum(v[1:], 1.0) - 1.0, 0.0)
    out = np.empty(R.shape, np.float64)
    flat_R, flat_d, flat_out = R.reshape(-1), delta.reshape(-1), out.reshape(-1)
    for s in range(0, flat_R.size, 16384):  # [pixels, gray levels] a block at a time
        r, d = flat_R[s:s + 16384, None], flat_d[s:s + 16384, None]
        Dp = D / (r + D * d)
        lit = np.log((Dp + 2.0) / (Dp + 1.0)) @ pmf[1:]
        with np.errstate(divide="ignore"):
            a0 = 1.0 / d[:, 0] + 1.0
        dark = np.where(d[:, 0] > 0, np.log1p(1.0 / a0), 0.0)
        flat_out[s:s + 16384] = lit + pmf[0] * dark
    return out
