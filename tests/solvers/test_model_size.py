"""A model's graph is bounded before anything derives or compiles it (issue 41, item 3).

Shared sub-expressions count once (CasADi's SX graph), so a deep chain of definitions that reuse
each other twice costs linear, not exponential, work; a model past the limit is refused naming the
largest equation, before a fit pays for its derivatives, kernels or compiled C.
"""
from __future__ import annotations

import pytest

from greyfit.schemas.model import Model
from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.model.compiler import MAX_MODEL_INSTRUCTIONS, compile_model


def _chain(depth: int) -> Model:
    defs = {"d0": "x"}
    for i in range(1, depth + 1):
        defs[f"d{i}"] = f"sin(d{i - 1})*cos(d{i - 1}) + d{i - 1}"
    return Model.model_validate({"states": ["x", "z"], "inputs": ["u"], "parameters": [{"name": "a", "value": 1.0}],
                                 "definitions": defs, "equations": {"z": "-z", "x": f"-a*d{depth} + u"}})


def test_a_deep_chain_of_shared_definitions_compiles_linearly():
    cm = compile_model(_chain(200))   # 2^200 terms as a tree; ~800 operations as a graph
    assert 600 < cm.rhs.n_instructions() < 1200


def test_a_model_past_the_size_limit_is_refused_naming_the_equation():
    depth = MAX_MODEL_INSTRUCTIONS // 4 + 100   # four operations a level
    with pytest.raises(ModelDefinitionError) as info:
        compile_model(_chain(depth))
    assert info.value.field == "equations.x"
    assert "limit is 20000" in str(info.value)
