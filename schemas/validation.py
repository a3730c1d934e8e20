"""Validation metrics: a model simulated on records, compared with the measured outputs."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import BaseModel, Field

# where an experiment's initial state came from
InitialStateSource = Literal[
    "experiment",     # the experiment's own `initial_state` (every state)
    "provided",       # `initial_states[experiment]` of the request (or of a previous fit's result)
    "contiguous",     # the state the estimation fit reached at the end of the record this one continues
    "estimated",      # the free states fitted on a short leading window, parameters fixed
]


class OutputMetrics(BaseModel):
    """Per output, over the measured (non-null) samples."""

    rmse: dict[str, float] = Field(default_factory=dict, description="root-mean-square error per output")
    fit_percent: dict[str, float] = Field(
        default_factory=dict, description="MATLAB compare: 100 (1 - |y - ŷ| / |y - mean(y)|)")
    nrmse: dict[str, float] = Field(
        default_factory=dict, description="|y - ŷ| / |y - mean(y)| = 1 - fit_percent/100 (RMSE over std)")


class ExperimentValidation(OutputMetrics):
    name: str = Field(description="the validation record's name")
    initial_state: dict[str, float] = Field(description="the initial state used")
    initial_state_source: InitialStateSource = Field(
        description="experiment (its own initial_state), provided, contiguous (where the estimation record ended) or "
                    "estimated")
    estimated_states: list[str] = Field(
        default_factory=list, description="states fitted on the leading window (source 'estimated')")
    estimate_window: Optional[int] = Field(
        default=None, description="samples of the leading window the free initial states were fitted on")
    note: Optional[str] = Field(default=None, description="a remark on this record, else null")
    time: Optional[list[float]] = Field(default=None, description="with simulated, when return_traces")
    simulated: Optional[dict[str, list[Optional[float]]]] = Field(
        default=None, description="simulated outputs on the record's time grid, when return_traces")


class ValidationResult(OutputMetrics):
    """Simulation metrics on records (pooled over experiments), and per experiment."""

    experiments: list[ExperimentValidation] = Field(description="per validation record, its metrics and initial state")
