"""One constraint compiler for ODE and transfer-function models: same g(p), same refusals."""
import casadi as ca
import numpy as np
import pytest

from greyfit.schemas.frequency import TransferFunctionModel
from greyfit.schemas.model import Model
from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.frequency.polynomials import compile_transfer_function
from greyfit.solvers.model.compiler import compile_model
from tests.frequency_systems import seed001_model
from tests.systems import msd_model

CONSTRAINTS = ["c - 0.1*k >= 0.2", "k <= 4*c", "c*k == 1.5"]


def test_ode_constraints_are_g_of_p_nonnegative_with_equalities_marked():
    cm = compile_model(Model.model_validate({**msd_model(), "constraints": CONSTRAINTS}))
    m, c, k = 2.0, 0.8, 5.0
    g = np.asarray(cm.constraint(ca.DM([m, c, k]))).ravel()
    np.testing.assert_allclose(g, [c - 0.1 * k - 0.2, 4 * c - k, c * k - 1.5], rtol=1e-14)
    assert cm.constraint_equality.tolist() == [False, False, True]


def test_ode_constraint_through_a_state_dependent_definition_is_refused():
    model = {**msd_model(), "definitions": {"spring": "k*x"}, "constraints": ["spring >= 0"]}
    with pytest.raises(ModelDefinitionError, match="only involve parameters") as err:
        compile_model(Model.model_validate(model))
    assert err.value.field == "constraints[0]"


def test_transfer_function_constraints_use_the_same_compiler():
    model = seed001_model({"b1": 1.0, "b2": 2.0, "a1": 3.0, "a2": 4.0, "a3": 5.0})
    model["constraints"] = ["a1*a2 - a3 >= 0.5", "b1 == Kp*b2"]
    tf = compile_transfer_function(TransferFunctionModel.model_validate(model))
    g = ca.Function("g", [tf.p], [tf.constraint])   # p in declaration order: a1, a2, a3, b1, b2
    np.testing.assert_allclose(np.asarray(g(ca.DM([3.0, 4.0, 5.0, 1.0, 2.0]))).ravel(), [6.5, -1.0])
    assert tf.constraint_equality.tolist() == [False, True]
    model["constraints"] = ["a1 >= w"]
    with pytest.raises(ModelDefinitionError, match="'w' is not one") as err:
        compile_transfer_function(TransferFunctionModel.model_validate(model))
    assert err.value.field == "model.constraints[0]"
