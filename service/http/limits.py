"""This server's size limits (settings), applied after the schema's own hard limits."""
from __future__ import annotations

from greyfit.schemas.fit import FitRequest
from greyfit.schemas.simulate import SimulateRequest
from greyfit.service.http.problems import LimitExceeded
from greyfit.service.settings import Settings


def check_limits(req: FitRequest, settings: Settings, prefix: str = "") -> None:
    """Raise LimitExceeded naming the field and the limit."""
    if len(req.experiments) > settings.max_experiments:
        raise LimitExceeded(f"{prefix}experiments", f"{len(req.experiments)} experiments, this server "
                            f"accepts at most {settings.max_experiments}; split the request")
    if len(req.model.parameters) > settings.max_parameters:
        raise LimitExceeded(f"{prefix}model.parameters", f"{len(req.model.parameters)} parameters, "
                            f"the limit is {settings.max_parameters}")
    _check_texts(_ode_texts(req.model), settings, f"{prefix}model.")
    records = [("experiments", req.experiments), ("validation", getattr(req, "validation", []))]
    for field, exps in records:
        for i, exp in enumerate(exps):
            if len(exp.time) > settings.max_samples_per_experiment:
                raise LimitExceeded(f"{prefix}{field}[{i}].time", f"{len(exp.time)} samples, the limit "
                                    f"is {settings.max_samples_per_experiment}; decimate or split the record")


def _ode_texts(model) -> dict[str, str]:
    texts = {f"equations.{k}": v for k, v in model.equations.items()}
    texts.update({f"definitions.{k}": v for k, v in model.definitions.items()})
    texts.update({f"outputs.{k}": v for k, v in (model.outputs or {}).items()})
    texts.update({f"constraints[{i}]": v for i, v in enumerate(model.constraints)})
    return texts


def _check_texts(texts: dict[str, str], settings: Settings, prefix: str) -> None:
    for where, text in texts.items():
        if len(text) > settings.max_expression_length:
            raise LimitExceeded(f"{prefix}{where}", f"{len(text)} characters, the limit is "
                                f"{settings.max_expression_length}; split it with definitions")


def check_simulate_limits(req, settings: Settings, prefix: str = "") -> None:
    """A simulation's records against the sample limit (its model is checked when it is built)."""
    for i, exp in enumerate(req.experiments):
        if len(exp.time) > settings.max_samples_per_experiment:
            raise LimitExceeded(f"{prefix}experiments[{i}].time", f"{len(exp.time)} samples, the limit is "
                                f"{settings.max_samples_per_experiment}; decimate or split the record")


def check_frequency_limits(req, settings: Settings, prefix: str = "") -> None:
    """A frequency-response fit (FrequencyFitRequest) against this server's limits, naming the field."""
    model = req.model
    if len(model.parameters) > settings.max_parameters:
        raise LimitExceeded(f"{prefix}model.parameters", f"{len(model.parameters)} parameters, the limit is "
                            f"{settings.max_parameters}")
    if len(req.data) > settings.max_experiments:
        raise LimitExceeded(f"{prefix}data", f"{len(req.data)} data sets, this server accepts at most "
                            f"{settings.max_experiments}; split the request")
    if getattr(model, "kind", None) == "linearised_ode":   # an ODE model: its equations and outputs
        texts = _ode_texts(model)
    else:
        texts = {f"{part}[{k}]": c for part in ("numerator", "denominator", "constraints")
                 for k, c in enumerate(getattr(model, part))}
    if model.feedback is not None:
        texts.update({f"feedback.controller.{part}[{k}]": c for part in ("num", "den")
                      for k, c in enumerate(getattr(model.feedback.controller, part))})
    _check_texts(texts, settings, f"{prefix}model.")
    series = [(f"data[{i}].omega", d.omega or []) for i, d in enumerate(req.data)]
    series += [(f"data[{i}].sine_tests[{j}].time", t.time) for i, d in enumerate(req.data)
               for j, t in enumerate(d.sine_tests or [])]
    for where, values in series:
        if len(values) > settings.max_samples_per_experiment:
            raise LimitExceeded(f"{prefix}{where}", f"{len(values)} samples, the limit is "
                                f"{settings.max_samples_per_experiment}; decimate the record")


def frequency_values(req) -> int:
    """How many numbers a frequency-response fit's data carry (the synchronous size measure)."""
    total = 0
    for d in req.data:
        total += 3 * len(d.omega or [])
        total += sum(3 * len(t.time) for t in d.sine_tests or [])
    return total


def data_values(req: FitRequest | SimulateRequest) -> int:
    """How many numbers the request's experiments carry (the synchronous size measure)."""
    total = 0
    for exp in list(req.experiments) + list(getattr(req, "validation", [])):
        series = 1 + len(exp.inputs) + len(exp.outputs) + len(exp.derivatives)
        total += series * len(exp.time)
    return total


def check_design_limits(req, settings: Settings, prefix: str = "") -> None:
    """An experiment design (DesignRequest) against this server's limits, naming the field.

    The design's cost grows with samples × free parameters² × starts (× draws, × rivals): the sample
    limit is the fit's, the models' sizes and texts are checked as a fit's are.
    """
    models = [("model.", req.model)] if req.model is not None else []
    models += [(f"rivals[{k}].model.", r.model) for k, r in enumerate(req.rivals)]
    for where, model in models:
        if len(model.parameters) > settings.max_parameters:
            raise LimitExceeded(f"{prefix}{where}parameters", f"{len(model.parameters)} parameters, the limit "
                                f"is {settings.max_parameters}")
        _check_texts(_ode_texts(model), settings, f"{prefix}{where}")
    samples = int(req.duration / req.sample_time) + 1
    if samples > settings.max_samples_per_experiment:
        raise LimitExceeded(f"{prefix}duration", f"{samples} samples (duration / sample_time), the limit is "
                            f"{settings.max_samples_per_experiment}; shorten it or sample more slowly")
    if req.baseline is not None and len(req.baseline.time) > settings.max_samples_per_experiment:
        raise LimitExceeded(f"{prefix}baseline.time", f"{len(req.baseline.time)} samples, the limit is "
                            f"{settings.max_samples_per_experiment}")


def design_values(req) -> int:
    """How many numbers a design carries and makes (the synchronous size measure): its grid and baseline."""
    total = (int(req.duration / req.sample_time) + 1) * (1 + len(req.inputs))
    if req.baseline is not None:
        total += (1 + len(req.baseline.inputs) + len(req.baseline.outputs)) * len(req.baseline.time)
    return total
