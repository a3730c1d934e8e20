"""What a result carries of its model: the model itself and the declared units of its parameters."""
from __future__ import annotations

from greyfit.schemas.fit import FitResult


def attach_model(result: FitResult, model) -> FitResult:
    """Put `model` into `result.model` and each declared `unit` onto its estimates.

    Parameters
    ----------
    result : FitResult
        A finished fit (changed in place and returned).
    model : Model, TransferFunctionModel or LinearisedOdeModel
        The model as the request declared it. Per-experiment copies (``k[e1]``) and time-varying
        samples (``k__3``) take the unit of the parameter they copy.

    Returns
    -------
    FitResult
        The same result, which `simulate` and `report` can now use without the request.
    """
    units = {p.name: p.unit for p in model.parameters if p.unit}
    for label, estimate in result.parameters.items():
        base = label.split("[", 1)[0]   # k[e1]: a per-experiment copy of k
        unit = units.get(base, units.get(base.rsplit("__", 1)[0]))   # k__3: a sample of a time-varying k
        if unit is not None and estimate.unit is None:
            estimate.unit = unit
    result.model = model
    return result
