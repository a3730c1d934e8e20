"""Per-experiment data preparation (window, detrend, decimate) and what was done, for the result."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, model_validator


class Preprocess(BaseModel):
    """Applied to every series of the experiment in this order: window, detrend, decimate."""

    model_config = ConfigDict(extra="forbid")

    window: Optional[tuple[float, float]] = Field(
        default=None, description="keep the samples with t0 <= t <= t1")
    detrend: Optional[Literal["mean", "linear"]] = Field(
        default=None, description="remove each input's and output's mean or least-squares line")
    decimate: Optional[int] = Field(
        default=None, ge=2, le=1000,
        description="keep every k-th sample after a zero-phase low-pass FIR anti-alias filter "
                    "(Hamming-windowed sinc of 20k+1 taps, cut-off at the new Nyquist frequency)")

    @model_validator(mode="after")
    def _window_is_ordered(self) -> "Preprocess":
        if self.window is not None and not self.window[0] < self.window[1]:
            raise ValueError(f"window {list(self.window)}: give [t0, t1] with t0 < t1")
        return self


class Hint(BaseModel):
    """Advice about the data or the options (the fit ran as requested)."""

    code: str = Field(description="a stable machine-readable code")
    message: str = Field(description="the hint in words")
    detail: dict = Field(description="the numbers behind it", default_factory=dict)


class ExperimentPreprocessing(BaseModel):
    name: str = Field(description="the record's name")
    samples_in: int = Field(description="samples in the record as sent")
    samples_out: int = Field(description="samples fitted after windowing and decimation")
    window: Optional[tuple[float, float]] = Field(default=None, description="the time window kept [s], else null")
    detrend: Optional[str] = Field(default=None, description="what was removed: mean or linear, else null")
    removed_trend: dict[str, list[float]] = Field(
        default_factory=dict, description="per series: [mean] or [intercept at the first sample, slope]")
    decimate: Optional[int] = Field(default=None, description="the decimation factor, else null")
    anti_alias_filter: Optional[str] = Field(
        default=None, description="the low-pass applied before decimating, else null")


class PreprocessingReport(BaseModel):
    experiments: list[ExperimentPreprocessing] = Field(
        description="per record, what preprocessing did to it", default_factory=list)
    hints: list[Hint] = Field(
        description="suggestions about the data (e.g. a sample rate far above the dynamics)", default_factory=list)
    input_interpolation: dict[str, Literal["foh", "zoh", "cubic"]] = Field(
        default_factory=dict, description="per input, how it was taken between samples: held (zoh), "
        "linear (foh) or a cubic through the samples (cubic); chosen from the data when "
        "options.input_interpolation is 'auto'")
    interpolation_note: Optional[str] = Field(default=None, description="why, when chosen automatically")
    input_refinement: Optional[int] = Field(
        default=None, description="points per sample interval of the finer grid the inputs were read on "
        "(a cubic reading); the outputs, residuals and counts stay those of the original samples")
    substeps: Optional[int] = Field(
        default=None, description="RK4 steps per sample interval chosen from the model's fastest mode "
        "along the simulation at the initial guess (options.substeps not given)")
    substeps_note: Optional[str] = Field(default=None, description="how the integrator substeps were chosen, else null")
