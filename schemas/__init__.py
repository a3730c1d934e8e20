"""Public contract of greyfit: pydantic models only (no numerics, no I/O)."""
from greyfit.schemas.experiment import Experiment
from greyfit.schemas.fit import (
    CovariancePublic,
    ExperimentTrace,
    FitMethod,
    FitMetrics,
    FitOptions,
    FitRequest,
    FitResult,
    MethodChoice,
    ParameterEstimate,
    ResidualAnalysis,
    SolverInfo,
)
from greyfit.schemas.model import Model, Parameter
from greyfit.schemas.preprocess import Preprocess
from greyfit.schemas.simulate import SimulateRequest, SimulateResult
from greyfit.schemas.validation import ValidationResult

__all__ = [
    "Model", "Parameter", "Experiment", "CovariancePublic", "FitMethod", "FitOptions",
    "FitRequest", "FitResult", "ParameterEstimate", "FitMetrics", "SolverInfo",
    "MethodChoice",
    "ExperimentTrace", "ResidualAnalysis", "Preprocess", "SimulateRequest", "SimulateResult",
    "ValidationResult",
]
