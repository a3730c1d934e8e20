"""linear_state_space templates: seed 002's shunt motor in four lines, same fit as the written-out model."""
import numpy as np
import pytest
from pydantic import ValidationError

from greyfit.schemas import FitRequest, Model
from greyfit.solvers.fit import fit_model
from tests.systems import MOTOR_A, MOTOR_B, motor_inputs, motor_model, motor_truth, simulate_motor

MOTOR_TEMPLATE = {
    "A": [["a11", "a12", 0], ["a21", "a22", "a23"], ["a31", "a32", "a33"]],
    "B": [["b11", 0, 0], [0, "b22", 0], [0, 0, "b33"]],
}


def _requests():
    t = np.linspace(0, 5, 1001)
    x, u = simulate_motor(t), motor_inputs(t)
    dx = MOTOR_A @ x + MOTOR_B @ u
    exp = {"name": "motor", "time": t.tolist(), "inputs": {f"u{i + 1}": u[i].tolist() for i in range(3)},
           "outputs": {f"x{i + 1}": x[i].tolist() for i in range(3)},
           "derivatives": {f"x{i + 1}": dx[i].tolist() for i in range(3)}}
    written = motor_model()
    template = {k: v for k, v in written.items() if k != "equations"}
    template["linear_state_space"] = MOTOR_TEMPLATE
    return ({"model": written, "experiments": [exp], "method": "equation_error"},
            {"model": template, "experiments": [exp], "method": "equation_error"})


def test_motor_template_fits_like_the_written_out_model():
    written, template = _requests()
    a = fit_model(FitRequest.model_validate(written))
    b = fit_model(FitRequest.model_validate(template))
    truth = motor_truth()
    for name, value in truth.items():
        assert b.parameters[name].value == pytest.approx(value, rel=1e-8)
        assert b.parameters[name].value == pytest.approx(a.parameters[name].value, rel=1e-12, abs=1e-12)
    # the expanded model survives a JSON round trip (workers re-validate it)
    m = FitRequest.model_validate(template).model
    assert Model.model_validate(m.model_dump(mode="json")) == m


def test_outputs_from_c_and_d_and_bad_shapes_name_the_field():
    m = Model.model_validate({"states": ["x1", "x2"], "inputs": ["u"],
                              "parameters": [{"name": "a", "value": -1.0}, {"name": "g", "value": 2.0}],
                              "linear_state_space": {"A": [[0, 1], ["-a^2", "-2*a"]], "B": [[0], ["g"]],
                                                     "C": [[1, 0]], "D": [[0.5]], "output_names": ["pos"]}})
    assert m.equations == {"x1": "x2", "x2": "(-a^2)*x1 + (-2*a)*x2 + (g)*u"}
    assert m.outputs == {"pos": "x1 + (0.5)*u"}
    with pytest.raises(ValidationError, match=r"linear_state_space.A\[1\]: 1 entries, states has 2"):
        Model.model_validate({"states": ["x1", "x2"], "linear_state_space": {"A": [[0, 1], [0]]}})
    with pytest.raises(ValidationError, match="either equations or linear_state_space"):
        Model.model_validate({"states": ["x"], "equations": {"x": "-x"}, "linear_state_space": {"A": [[-2]]}})
