"""How a measurement file's columns become a record: the options of `greyfit fit --data`, of
`greyfit.Experiment.from_csv` and of POST /v1/fits/files, in one place."""
from __future__ import annotations

from typing import Annotated, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, model_validator

from greyfit.schemas.model import FiniteFloat, Name
from greyfit.schemas.preprocess import Preprocess

# seconds per unit of a time column
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9, "min": 60.0, "h": 3600.0}
Column = Annotated[str, StringConstraints(min_length=1, max_length=256)]


class FileColumns(BaseModel):
    """Which column is time and which is each of the model's inputs and outputs, their units, and the
    part of the record to keep. Columns are matched to the model's names as written in the header
    (`x`, or `x [m]` with a unit in brackets); `columns` maps the names that differ."""

    model_config = ConfigDict(extra="forbid")

    time: Optional[Column] = Field(
        default=None, description="the time column; default: a column named t or time. Not with sample_rate")
    sample_rate: Optional[float] = Field(
        default=None, gt=0, allow_inf_nan=False,
        description="samples per second, for a file without a time column: t = i / sample_rate")
    time_unit: Literal["s", "ms", "us", "ns", "min", "h"] = Field(
        default="s", description="the unit of the time column; converted to seconds")
    columns: dict[Name, Column] = Field(
        default_factory=dict, description="model input or output -> the file's column, where they differ")
    scale: dict[Name, FiniteFloat] = Field(
        default_factory=dict, description="model input or output -> factor the column is multiplied by "
        "(e.g. 0.001 for a column in mm and a model in m)")
    start: Optional[FiniteFloat] = Field(
        default=None, description="keep the samples from this time on (seconds): a segment of the record")
    stop: Optional[FiniteFloat] = Field(default=None, description="keep the samples up to this time (seconds)")
    decimate: Optional[int] = Field(
        default=None, ge=2, le=1000, description="keep every k-th sample, after an anti-alias filter")
    remove_means: bool = Field(default=False, description="subtract each input's and output's mean")

    @model_validator(mode="after")
    def _one_clock(self) -> "FileColumns":
        if self.time is not None and self.sample_rate is not None:
            raise ValueError("give the time column or the sample rate, not both")
        if self.start is not None and self.stop is not None and not self.start < self.stop:
            raise ValueError(f"the segment from {self.start} to {self.stop} s is empty: start before stop")
        return self

    def preprocess(self, first: float, last: float) -> Optional[Preprocess]:
        """The segment, decimation and mean removal as the `preprocess` of a record from `first` to `last`
        seconds (the result's `preprocessing` says what was done)."""
        segment = self.start is not None or self.stop is not None
        if not segment and self.decimate is None and not self.remove_means:
            return None
        window = (first if self.start is None else self.start, last if self.stop is None else self.stop)
        return Preprocess(window=window if segment else None, decimate=self.decimate,
                          detrend="mean" if self.remove_means else None)
