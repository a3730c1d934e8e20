"""The whitelist grammar: what compiles, and every refusal naming the field and column."""
import casadi as ca
import pytest

from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.model.expressions import MAX_DEPTH, compile_expression

X, K = ca.SX.sym("x"), ca.SX.sym("k")
ENV = {"x": X, "k": K}


def evaluate(text, x=0.7, k=2.0):
    expr = compile_expression(text, ENV, "equations.v")
    return float(ca.Function("f", [X, K], [expr])(x, k))


@pytest.mark.parametrize("text, expected", [
    ("-k*x^2", -2.0 * 0.49),
    ("-x**2", -0.49),
    ("2^3^2", 2.0 ** 9),
    ("k - x - 1", 2 - 0.7 - 1),
    ("k / x / 2", 2 / 0.7 / 2),
    ("if_else(x > 0.5, k, -k)", 2.0),
    ("if_else(x <= 0.5, k, -k)", -2.0),
    ("atan2(x, k) + min(x, k) + max(x, k) + pow(k, 3)", 0.3366748193867272 + 0.7 + 2 + 8),
    ("sqrt(abs(-x)) * sign(-k) + exp(log(k)) + log10(100)", -(0.7 ** 0.5) + 2 + 2),
    ("tanh(0) + sinh(0) + cosh(0) + asin(0) + acos(1) + atan(0) + tan(0) + sin(0) + cos(0)", 2.0),
    ("1.5e-3 * 2E+3 + .5", 3.5),
    ("pi - pi + e - e", 0.0),
])
def test_grammar_computes(text, expected):
    assert evaluate(text) == pytest.approx(expected, rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("text, fragment", [
    ("k*kk", "unknown name 'kk' at column 3"),
    ("__import__('os')", "unexpected character"),
    ("open(x)", "unknown function 'open'"),
    ("x.real", "unexpected character '.' at column 2"),
    ("x +", "expected a number, name or '('"),
    ("(x", "expected ')'"),
    ("x)", "unexpected ')'"),
    ("min(x)", "min takes 2 argument(s), got 1"),
    ("if_else(x, k)", "if_else takes 3 argument(s)"),
    ("x < k < 1", "chained comparison"),
    ("", "empty expression"),
    ("x; k", "unexpected character ';'"),
    ("lambda: 1", "unexpected character ':'"),
])
def test_refusals_name_field_and_position(text, fragment):
    with pytest.raises(ModelDefinitionError) as info:
        compile_expression(text, ENV, "equations.v")
    assert str(info.value).startswith("equations.v: ")
    assert fragment in str(info.value)


def test_depth_and_length_are_limited_without_recursion_errors():
    deep = "(" * (MAX_DEPTH + 1) + "x" + ")" * (MAX_DEPTH + 1)
    with pytest.raises(ModelDefinitionError, match="nested deeper"):
        compile_expression(deep, ENV, "equations.v")
    with pytest.raises(ModelDefinitionError, match="nested deeper"):
        compile_expression("-" * 1000 + "x", ENV, "equations.v")
    with pytest.raises(ModelDefinitionError, match="limit is 4000"):
        compile_expression("(" * 10 ** 6 + "x" + ")" * 10 ** 6, ENV, "equations.v")
    assert evaluate("(" * 30 + "x" + ")" * 30) == pytest.approx(0.7)
