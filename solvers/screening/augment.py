"""Rewrite a model with a new effect: a term added to an equation, or a parameter made variable."""
from __future__ import annotations

from greyfit.schemas.model import Model
from greyfit.solvers.model.expressions import parse, substitute, unparse
from greyfit.solvers.screening.canonical import canonical_form


def add_term(model: Model, equation: str, term: str, sign: str = "+") -> Model:
    """Add `sign term` to d(equation)/dt.

    Where every term of the equation is divided by the same parameters or constants (a mass, a heat
    capacity: `(forces)/m`, however it is spelt), the new term is divided by them too, so that its
    parameter keeps physical units (a force, not a force per mass) and the same value for every
    spelling of the model (`canonical.CanonicalForm.divisors`).

    Parameters
    ----------
    model : Model
        The model (not changed).
    equation : str
        The state whose equation gets the term.
    term : str
        The term (model expression syntax).
    sign : str
        "+" or "-".

    Returns
    -------
    Model
        A copy with the rewritten equation.

    Raises
    ------
    ModelDefinitionError
        When the equation does not parse (`equations.<state>`).
    """
    node = parse(model.equations[equation], f"equations.{equation}")
    divisors = canonical_form(model).divisors.get(equation, ())
    added = f"{term}/({'*'.join(divisors)})" if divisors else term
    equations = dict(model.equations)
    equations[equation] = f"{unparse(node)} {sign} {added}"
    return model.model_copy(update={"equations": equations})


def replace_parameter(model: Model, name: str, replacement: str) -> Model:
    """Replace parameter `name` by an expression everywhere it is used (equations, definitions, outputs).

    Parameters
    ----------
    model : Model
        The model (not changed).
    name : str
        The parameter (or any name) to replace.
    replacement : str
        The expression that takes its place (model syntax).

    Returns
    -------
    Model
        A copy with the name substituted in the equations, definitions and declared outputs.

    Raises
    ------
    ModelDefinitionError
        When the replacement or a rewritten expression does not parse.
    """
    return _substitute_name(model, name, replacement, in_outputs=True)


def _substitute_name(model: Model, name: str, replacement: str, in_outputs: bool) -> Model:
    rep = parse(replacement, "replacement")

    def rewrite(text: str, where: str) -> str:
        return unparse(substitute(parse(text, where), name, rep))

    update = {
        "equations": {k: rewrite(v, f"equations.{k}") for k, v in model.equations.items()},
        "definitions": {k: rewrite(v, f"definitions.{k}") for k, v in model.definitions.items()},
    }
    if in_outputs and model.outputs is not None:
        update["outputs"] = {k: rewrite(v, f"outputs.{k}") for k, v in model.outputs.items()}
    return model.model_copy(update=update)


def with_parameter(model: Model, name: str, value: float, lower=None, upper=None, unit=None,
                   per_experiment: bool = False) -> Model:
    """The model with one more parameter declared.

    Parameters
    ----------
    model : Model
        The model (not changed).
    name : str
        The new parameter's name (see `fresh_name`).
    value : float
        Its initial value.
    lower, upper : float or None
        Its bounds; None: unbounded.
    unit : str or None
        Its unit, for the report.
    per_experiment : bool
        Whether it takes one value per experiment.

    Returns
    -------
    Model
        A copy with the parameter appended.
    """
    from greyfit.schemas.model import Parameter
    params = list(model.parameters) + [Parameter(name=name, value=value, lower=lower, upper=upper,
                                                 unit=unit, per_experiment=per_experiment)]
    return model.model_copy(update={"parameters": params})


def fresh_name(model: Model, stem: str) -> str:
    """A name not yet used in the model: `stem`, else `stem_2`, `stem_3`, ...

    Parameters
    ----------
    model : Model
        The model whose states, inputs, parameters, constants and definitions are taken.
    stem : str
        The wanted name.

    Returns
    -------
    str
        `stem` or the first free ``stem_<i>``, i ≥ 2.
    """
    used = set(model.states) | set(model.inputs) | {p.name for p in model.parameters} | \
        set(model.constants) | set(model.definitions)
    if stem not in used:
        return stem
    i = 2
    while f"{stem}_{i}" in used:
        i += 1
    return f"{stem}_{i}"


def replace_in_equations(model: Model, name: str, replacement: str) -> Model:
    """Replace a state (or any name) by an expression in the state equations and definitions only.

    The output equations keep measuring the state itself (a level sensor still reads the level).

    Parameters
    ----------
    model : Model
        The model (not changed).
    name : str
        The name to replace.
    replacement : str
        The expression that takes its place (model syntax).

    Returns
    -------
    Model
        A copy with the name substituted in the equations and definitions.

    Raises
    ------
    ModelDefinitionError
        When the replacement or a rewritten expression does not parse.
    """
    return _substitute_name(model, name, replacement, in_outputs=False)


def rewrite_output(model: Model, output: str, template: str) -> Model:
    """Output `output` becomes `template` with `{h}` standing for its declared expression.

    Parameters
    ----------
    model : Model
        The model (not changed); all its measured outputs are written out explicitly.
    output : str
        The measured output to rewrite.
    template : str
        The new expression, ``{h}`` standing for the old one (e.g. ``"{h} + b"``).

    Returns
    -------
    Model
        A copy with the rewritten output.
    """
    outputs = model.measured_outputs()
    outputs[output] = template.format(h=f"({outputs[output]})")
    return model.model_copy(update={"outputs": outputs})
