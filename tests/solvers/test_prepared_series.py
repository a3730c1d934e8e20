"""A request's series is converted to an array once per fit (`series_array` within `prepared_once`):
the input check, the solve's records and the noise-level check share it, read-only."""
import numpy as np

import greyfit
from greyfit.solvers.data.experiments import prepare_experiments, prepared_once, series_array
from greyfit.solvers.data.preprocess import held_inputs
from greyfit.solvers.model.compiler import compile_model
from tests.servers import msd_request


def test_a_fit_converts_each_series_of_the_request_once():
    """Within a fit (`prepared_once`) a request's list becomes one shared, read-only array: the input
    check, the solve's records and the noise-level check read the same conversion."""
    request = greyfit.FitRequest.model_validate(msd_request(0))
    exp = request.experiments[0]
    outside = series_array(exp.time)
    assert outside.flags.writeable and outside is not series_array(exp.time)
    with prepared_once():
        data = prepare_experiments(request.experiments, compile_model(request.model))[0]
        shared = series_array(exp.time)
        assert shared is series_array(exp.time) and not shared.flags.writeable
        assert np.shares_memory(data.t, shared)
        assert held_inputs(request.experiments)["u"][0] is False   # the sum of sines is not held
        assert series_array(exp.inputs["u"]) is series_array(exp.inputs["u"])
        np.testing.assert_array_equal(data.u[0], series_array(exp.inputs["u"]))
    assert series_array(exp.time) is not shared                    # nothing is kept after the fit
