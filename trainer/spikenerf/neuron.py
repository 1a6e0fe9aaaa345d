"""The differentiable spike sensor: radiance -> expected spike counts (sensor-model.md).

Rate per frame ``lambda = R * ((I / 256) X + d)``. The integrate-and-fire pixel starts at
``A0 ~ U(0, 1)``, adds ``lambda`` each frame, fires at ``A >= 1`` and *subtracts* the
threshold. For a constant rate over ``n`` frames its count is ``floor(A0 + n lambda)``
(one spike a frame at most, so capped at ``n``); over the uniform start phase its
expectation is exactly ``n * min(lambda, 1)``: a closed form, no loop over frames.
Consecutive windows of one stream hand their residual charge on, so each window's count is
``floor(A_w + n lambda)`` with the same expectation.

Reset to zero (the ``reset_to_zero`` effect) would discard the residual: the pixel then
needs ``ceil(1 / lambda)`` frames per spike, so the rate becomes ``1 / ceil(1 / lambda)``, a
staircase that is biased low (``lambda = 0.6`` gives 0.5) and has zero gradient almost
everywhere. :func:`expected_count` supports it with a straight-through gradient (the slope
of ``1 / (1 / lambda + 1/2)``), for datasets made with that effect.

The published SpikeNeRF pixel (:func:`paper_pixel`, method ``spikenerf-paper``) is a different
model, ported as published: its interval-domain fixed-pattern formula (:func:`paper_fpn`), an
integrate-and-fire loop of 256 steps from an empty membrane with reset to zero
(:class:`PaperIF`), and the gamma 1/2.2 of its target images.
"""
from __future__ import annotations

import torch


def spike_rate(x: torch.Tensor, intensity: float, resp: torch.Tensor | None, dark: torch.Tensor | None) -> torch.Tensor:
    """``lambda = R ((I/256) X + d)`` in spikes per frame; same shape as ``x``."""
    lam = x * (float(intensity) / 256.0)
    if dark is not None:
        lam = lam + dark
    if resp is not None:
        lam = lam * resp
    return lam


def expected_count(lam: torch.Tensor, frames, reset: str = "subtract") -> torch.Tensor:
    """Mean spike count over ``frames`` frames (tensor or number) of a constant rate ``lam``."""
    lam = lam.clamp(min=0.0)
    if reset == "subtract":
        return frames * lam.clamp(max=1.0)
    if reset != "zero":
        raise ValueError(f"reset must be 'subtract' or 'zero', got {reset!r}")
    safe = lam.clamp(min=1e-6)
    stair = 1.0 / torch.ceil(1.0 / safe - 1e-9)
    smooth = 1.0 / (1.0 / safe + 0.5)
    rate = smooth + (stair - smooth).detach()
    return frames * torch.where(lam > 1e-6, rate, torch.zeros_like(rate))


def count_variance(mu: torch.Tensor, electrons: float = 0.0, temporal: float = 0.0,
                   jitter: float = 0.0) -> torch.Tensor:
    """Variance of an observed window count around its mean ``mu``.

    ``floor(A + m)`` with a uniform residual ``A`` has variance ``f (1 - f)`` (``f`` the
    fraction of ``m``), 1/6 on average; shot noise adds ``mu / N_e``; ``temporal`` is any
    further noise variance per expected spike (e.g. a generator's per-frame noise). A threshold
    jitter of relative SD ``jitter`` (the sensor's ``threshold_jitter``: the reset subtracts the
    nominal threshold, so it does not accumulate) moves only the spikes at the window's two ends
    and adds about ``2 jitter^2`` whatever the window's length (measured against the simulator in
    tests/test_trainer_neuron.py); its mean count is unchanged.
    """
    var = torch.full_like(mu, 1.0 / 6.0 + 2.0 * float(jitter) ** 2)
    if electrons > 0:
        var = var + mu / electrons
    if temporal > 0:
        var = var + temporal * mu
    return var


def rsir_rate(x: torch.Tensor, intensity: float, resp: torch.Tensor | None, dark: torch.Tensor | None) -> torch.Tensor:
    """Mean charge per frame (= spikes per frame) of the ``rsir`` reference generator (sensor-model.md).

    Per frame ``v ~ Poisson(m)``, ``m = I X 255/256``; ``D = 255/v - 1``; ``D' = D / (R + D d)``;
    ``q = 1 / (D' + U + 1)`` with ``U ~ U(0, 1)``, whose mean over U is ``ln((a + 1) / a)``,
    ``a = D' + 1``; ``v = 0`` gives ``D' = 1/d``. Summed over v with Poisson weights (a truncated,
    differentiable sum), so the generator's compression at high intensity (``q`` is 10 % below
    the linear ``I X / 256`` at I = 64, X = 1) is modelled instead of read as darker radiance.
    """
    m = (x * (float(intensity) * 255.0 / 256.0)).clamp(min=1e-8)
    v_max = int(float(intensity) + 6.0 * float(intensity) ** 0.5 + 6)
    v = torch.arange(0, v_max + 1, device=x.device, dtype=x.dtype)
    logp = v * torch.log(m)[..., None] - m[..., None] - torch.lgamma(v + 1)  # [..., V]
    resp = torch.ones_like(x) if resp is None else resp.expand_as(x)
    dark = torch.zeros_like(x) if dark is None else dark.expand_as(x)
    D = (255.0 / v[1:].clamp(min=1) - 1).clamp(min=0)  # [V-1]; v > 255 would be a negative interval
    Dp = D / (resp[..., None] + D * dark[..., None])
    q_lit = torch.log((Dp + 2) / (Dp + 1))  # mean over U of 1 / (D' + U + 1)
    a0 = 1.0 / dark.clamp(min=1e-12) + 1
    q_dark = torch.where(dark > 0, torch.log((a0 + 1) / a0), torch.zeros_like(dark))
    q = torch.cat([q_dark[..., None], q_lit], dim=-1)
    return (torch.exp(logp) * q).sum(dim=-1)


PAPER_STEPS = 256  # the published loop's length (and its count's divisor)
PAPER_GAMMA = 2.2  # the published output is (count / 256) ** (1 / 2.2)
PAPER_LUX = 335.0  # the published D_light is the interval at this illuminance


def paper_fpn_maps(resp: torch.Tensor, dark: torch.Tensor, lux_to_rate: float):
    """The published fixed-pattern maps ``(Nl, Nd, D_light)`` from this project's ``R`` and ``d``.

    ``Nl = R``; ``Nd = d / L`` (dark current in lux-equivalent, ``L`` spikes per frame per lux);
    ``D_light = 1 / (R L (335 + Nd))``, the interval (as ``1 / p``) at 335 lux. In its linear
    regime the published formula gives ``Nl x + Nd / (D_light (335 + Nd)) = R x + R d``: the
    dataset's own rate law, whatever ``L`` (it cancels; it only sets the parameterisation).
    """
    nd = dark / lux_to_rate
    return resp, nd, 1.0 / (resp * lux_to_rate * (PAPER_LUX + nd))


def paper_fpn(x: torch.Tensor, nl: torch.Tensor, nd: torch.Tensor, d_light: torch.Tensor) -> torch.Tensor:
    """The published fixed-pattern formula on a charge per frame ``x``, in the interval domain:
    ``D = 1/(x + 1e-5) - 1``; ``D' = D / (Nl + D Nd / (D_light (335 + Nd)))``; ``x' = 1/(D' + 1)``."""
    D = 1.0 / (x + 1e-5) - 1.0
    Dp = D / (nl + D * nd / (d_light * (PAPER_LUX + nd)))
    return 1.0 / (Dp + 1.0)


class PaperIF(torch.autograd.Function):
    """``count / steps`` of the published integrate-and-fire loop on a constant input ``c``.

    Forward, as published: the membrane starts at 0, adds ``c`` each of ``steps`` steps, fires
    when it is strictly above 1 and is then reset to 0 (float32 sums, as a loop computes
    them). Backward, as the published surrogate: a spike passes its gradient to the membrane,
    i.e. to every input since the last reset, so ``d(count / steps) / dc`` is the step of the
    last spike over ``steps`` (about 1; 0 without a spike): a straight-through estimator.
    """

    @staticmethod
    def forward(ctx, c: torch.Tensor, steps: int = PAPER_STEPS) -> torch.Tensor:
        m = torch.zeros_like(c)
        count = torch.zeros_like(c)
        last = torch.zeros_like(c)
        zero = torch.zeros_like(c)
        for t in range(1, steps + 1):
            m = m + c
            fire = m > 1.0
            count = count + fire.to(c.dtype)
            last = torch.where(fire, float(t), last)
            m = torch.where(fire, zero, m)
        ctx.save_for_backward(last / steps)
        return count / steps

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (slope,) = ctx.saved_tensors
        return grad * slope, None


def paper_pixel(x: torch.Tensor, intensity: float, nl: torch.Tensor, nd: torch.Tensor, d_light: torch.Tensor,
                steps: int = PAPER_STEPS) -> torch.Tensor:
    """The published pixel: ``x (I / 256)`` -> :func:`paper_fpn` -> :class:`PaperIF` -> ``** (1 / 2.2)``.

    ``x`` is the rendered linear luminance (the published code divides by 4: ``I = 64``).
    A pixel without a spike gives 0 with zero gradient (no infinite slope of the power at 0).
    """
    rate = PaperIF.apply(paper_fpn(x * (float(intensity) / 256.0), nl, nd, d_light), steps)
    lit = rate > 0
    return torch.where(lit, rate.clamp(min=1e-12) ** (1.0 / PAPER_GAMMA), torch.zeros_like(rate))
