"""Figures of a frequency-response fit: Bode magnitude and phase, and Nyquist, of data and model.

Everything comes from the result's `frequency_response` (measured and fitted G(jω) per data set,
i.e. per closed loop the data were measured on), so no request is needed. The model is drawn on a
dense grid from the fitted closed-loop numerator and denominator each data set carries (the model
at the estimates, with that data set's constants), not only at the measured frequencies: a lightly
damped resonance between two of them would otherwise be a chord.
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.frequency import DataSetResponse, FrequencyResponseResult

MAX_LOOPS = 4   # columns; the notes say when more data sets were left out
MODEL_POINTS = 400   # log-spaced frequencies of the model's curve
MODEL_MARGIN = 1.5   # the curve spans the data's frequencies widened by this factor at each end


def _complex(re: list[float], im: list[float]) -> np.ndarray:
    return np.asarray(re, dtype=float) + 1j * np.asarray(im, dtype=float)


def _phase_deg(g: np.ndarray) -> np.ndarray:
    """Unwrapped along ω, so a phase that passes -180° is drawn as one curve."""
    return np.degrees(np.unwrap(np.angle(g)))


def _db(g: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return 20 * np.log10(np.abs(g))


def model_response(ds: DataSetResponse, points: int = MODEL_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """The fitted model's G(jω) on a dense grid: (ω, G) for the model's curve.

    The grid is `points` log-spaced frequencies over the data's range widened by `MODEL_MARGIN` at
    each end, with the data's own frequencies and the natural frequencies |p| of the complex poles in
    that range added (so the curve passes through the fitted values at the data and reaches the
    resonance peaks). G is `solvers.frequency.response.numeric_response` of the data set's fitted
    closed-loop numerator and denominator. Where those cannot be evaluated (no coefficients, nothing
    finite) the curve is the fitted values at the data's frequencies, as the result holds them.
    """
    from greyfit.solvers.frequency.response import numeric_response
    from greyfit.solvers.frequency.stability import poles
    w = np.asarray(ds.omega, dtype=float)
    fitted = _complex(ds.fitted_real, ds.fitted_imag)
    num, den = np.asarray(ds.numerator, dtype=float), np.asarray(ds.denominator, dtype=float)
    positive = w[np.isfinite(w) & (w > 0)]
    if not (positive.size and num.size and den.size and np.all(np.isfinite(num)) and np.all(np.isfinite(den))):
        return w, fitted
    lo, hi = positive.min() / MODEL_MARGIN, positive.max() * MODEL_MARGIN
    p = poles(den)
    natural = np.abs(p[np.isfinite(p) & (np.abs(p.imag) > 0)])
    grid = np.unique(np.concatenate([np.geomspace(lo, hi, points), positive,
                                     natural[(natural >= lo) & (natural <= hi)]]))
    with np.errstate(all="ignore"):
        g = numeric_response(num, den, grid)
    return (grid, g) if np.isfinite(g).any() else (w, fitted)


def _fit_percent(measured: np.ndarray, fitted: np.ndarray) -> float:
    spread = np.linalg.norm(measured - measured.mean())
    return float(100 * (1 - np.linalg.norm(fitted - measured) / spread)) if spread > 0 else float("nan")


def _bode_column(ax_mag, ax_phase, ds: DataSetResponse, short) -> None:
    w = np.asarray(ds.omega, dtype=float)
    g, gh = _complex(ds.measured_real, ds.measured_imag), _complex(ds.fitted_real, ds.fitted_imag)
    wm, gm = model_response(ds)
    # data as markers, the model as a line: both stay visible where they agree
    ax_mag.semilogx(w, _db(g), "o", ms=3.5, mfc="none", color="0.35", label="measured")
    ax_mag.semilogx(wm, _db(gm), "-", lw=1.3, color="C0", label=f"model (fit {_fit_percent(g, gh):.1f} %)")
    ax_phase.semilogx(w, _phase_deg(g), "o", ms=3.5, mfc="none", color="0.35")
    ax_phase.semilogx(wm, _phase_deg(gm), "-", lw=1.3, color="C0")
    ax_mag.set_title(f"Bode: {short(ds.name)}", fontsize=9)
    ax_mag.set_ylabel("|G(jω)| [dB]")
    ax_phase.set_ylabel("∠G(jω) [deg]")
    ax_phase.set_xlabel("ω [rad/s]")
    ax_mag.legend(fontsize=7, frameon=False, loc="best")
    for ax in (ax_mag, ax_phase):
        ax.grid(True, which="major", lw=0.3, color="0.85")


def _nyquist_axes(ax, ds: DataSetResponse, short) -> None:
    g = _complex(ds.measured_real, ds.measured_imag)
    wm, gm = model_response(ds)
    ax.plot(g.real, g.imag, "o", ms=3.5, mfc="none", color="0.35", label="measured")
    ax.plot(gm.real, gm.imag, "-", lw=1.3, color="C0", label="model")
    ax.plot(gm.real[:1], gm.imag[:1], ">", color="C0", ms=5, label=f"model at ω = {wm[0]:.3g} rad/s")
    ax.axhline(0, color="0.75", lw=0.6)
    ax.axvline(0, color="0.75", lw=0.6)
    ax.set_title(f"Nyquist: {short(ds.name)}", fontsize=9)
    ax.set_xlabel("Re G(jω)")
    ax.set_ylabel("Im G(jω)")
    ax.legend(fontsize=7, frameon=False, loc="best")


def frequency_figures(plt, response: FrequencyResponseResult, svg: bool, notes: list[str]) -> list:
    """[Bode figure, Nyquist figure], one column per data set (at most MAX_LOOPS)."""
    from greyfit.service.report.page import _grid_layout  # (report imports this)
    from greyfit.service.report.page import _save as save
    from greyfit.service.report.page import _short as short
    sets = [d for d in response.data if len(d.omega) > 0]
    if not sets:
        notes.append("frequency response: no data set with frequencies to draw")
        return []
    if len(sets) > MAX_LOOPS:
        notes.append(f"frequency response: the first {MAX_LOOPS} of {len(sets)} data sets are drawn")
        sets = sets[:MAX_LOOPS]
    n = len(sets)
    fig, axes = plt.subplots(2, n, figsize=(4.6 * n, 5.4), squeeze=False, sharex="col")
    for c, ds in enumerate(sets):
        _bode_column(axes[0][c], axes[1][c], ds, short)
    _grid_layout(fig, 2, n, left=0.9, bottom=0.55, top=0.3, wgap=0.95, hgap=0.25)
    figures = [save(plt, fig, "bode", "Bode magnitude and phase of each data set: measured (circles) and the "
                    "fitted model's closed-loop response (line, on a dense grid of frequencies)", svg)]
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 4.2), squeeze=False)
    for c, ds in enumerate(sets):
        _nyquist_axes(axes[0][c], ds, short)
    _grid_layout(fig, 1, n, left=0.9, bottom=0.55, top=0.3, wgap=0.95)
    figures.append(save(plt, fig, "nyquist", "Nyquist plot of each data set: measured (circles) and the fitted "
                        "model (line, arrow at the lowest frequency)", svg))
    return figures
