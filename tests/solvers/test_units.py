"""Units of parameters that declare none, from the equations they enter (solvers/model/units.py),
and on the parameters a discovery adds."""
import pytest

from greyfit.schemas.model import Model
from greyfit.solvers.model.units import parameter_units, read_unit, write_unit


def msd_with_extras(**units) -> Model:
    return Model.model_validate({
        "name": "msd", "states": ["x", "v"], "inputs": ["u"],
        "parameters": [{"name": "m", "value": 2, "unit": "kg"}, {"name": "c", "value": 1, "unit": "N s/m"},
                       {"name": "k", "value": 1, "unit": "N/m"}, {"name": "k3", "value": 0},
                       {"name": "Fc", "value": 0}, {"name": "eps", "value": 0.01}, {"name": "a", "value": 0}],
        "equations": {"x": "v + a*x", "v": "(u - c*v - k*x - k3*x^3 - Fc*tanh(v/eps))/m"},
        "units": units})


def test_units_follow_from_the_terms_beside_them_and_from_the_state_over_time():
    found = parameter_units(msd_with_extras(x="m", v="m/s", u="N", t="s"))
    # k3 x^3 beside u [N]; Fc beside it too; tanh's argument has no unit; a x beside v [m/s] in dx/dt
    assert found == {"k3": "N/m^3", "Fc": "N", "eps": "m/s", "a": "1/s"}


def test_nothing_is_guessed_where_the_units_do_not_fix_it():
    assert parameter_units(msd_with_extras()) == {}    # no state, input or time units: every term undetermined
    # u without a unit: c v and k x (both N) still fix k3 beside them
    assert parameter_units(msd_with_extras(x="m", v="m/s"))["k3"] == "N/m^3"


@pytest.mark.parametrize("text, unit", [("N s/m", {"N": 1, "s": 1, "m": -1}), ("m/s^2", {"m": 1, "s": -2}),
                                        ("kg m**2", {"kg": 1, "m": 2}), ("1/s", {"s": -1}), ("1", {})])
def test_unit_text_reads_and_writes_back(text, unit):
    assert read_unit(text) == unit
    assert read_unit(write_unit(read_unit(text))) == unit
