"""Units and the model travel into the result, and survive its JSON."""
import numpy as np
import pytest

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.frequency import TransferFunctionModel
from greyfit.schemas.model import Model
from greyfit.solvers.fit import fit_model
from tests.systems import MSD_TRUTH, msd_experiment, msd_model, simulate_msd


def test_units_reach_per_experiment_copies_and_the_model_survives_json():
    t = np.linspace(0, 10, 101)
    model = msd_model()
    model["parameters"][1].update(unit="N s/m")
    model["parameters"][2].update(unit="N/m", per_experiment=True)
    model["units"] = {"x": "m", "t": "s"}
    request = FitRequest.model_validate({"model": model, "experiments": [
        msd_experiment(t, simulate_msd(t), noise=0.002, seed=s, name=f"e{s}") for s in (1, 2)]})
    result = fit_model(request)
    assert result.parameters["c"].unit == "N s/m"
    assert {result.parameters[f"k[e{s}]"].unit for s in (1, 2)} == {"N/m"}
    assert result.parameters["m"].unit is None   # none declared
    for s in (1, 2):   # the truth, so the copies are the fitted ones
        assert result.parameters[f"k[e{s}]"].value == pytest.approx(MSD_TRUTH["k"], rel=0.02)
    again = FitResult.model_validate_json(result.model_dump_json())
    assert isinstance(again.model, Model) and again.model.units == {"x": "m", "t": "s"}
    assert again.model.equations == request.model.equations


def test_a_frequency_result_carries_its_transfer_function():
    from greyfit.schemas.frequency import FrequencyFitRequest
    from greyfit.solvers.frequency import fit_frequency_response
    from tests.frequency_systems import TRUTH, frequency_data, seed001_model
    body = {"model": seed001_model({n: 1.2 * v for n, v in TRUTH.items()}),
            "data": [frequency_data(TRUTH, 1, 1, seed=5, name="pi")]}
    body["model"]["parameters"][0]["unit"] = "1/s"
    result = fit_frequency_response(FrequencyFitRequest.model_validate(body))
    again = FitResult.model_validate_json(result.model_dump_json())
    assert isinstance(again.model, TransferFunctionModel)
    assert again.parameters[body["model"]["parameters"][0]["name"]].unit == "1/s"
