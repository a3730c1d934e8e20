"""Public contract of greyfit: pydantic models only (no numerics, no I/O)."""
from schemas.model import Model, Parameter
from schemas.experiment import Experiment
from schemas.fit import (
    CovariancePublic,
    FitMethod,
    FitOptions,
    FitRequest,
    FitResult,
    ParameterEstimate,
    FitMetrics,
    SolverInfo,
    ExperimentTrace,
    ResidualAnalysis,
)
from schemas.preprocess import Preprocess
from schemas.simulate import SimulateRequest, SimulateResult
from schemas.validation import ValidationResult

__all__ = [
    "Model", "Parameter", "Experiment", "CovariancePublic", "FitMethod", "FitOptions",
    "FitRequest", "FitResult", "ParameterEstimate", "FitMetrics", "SolverInfo",
    "ExperimentTrace", "ResidualAnalysis", "Preprocess", "SimulateRequest", "SimulateResult",
    "ValidationResult",
]
