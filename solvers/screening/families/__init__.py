"""The effect library as a registry of families: one module per family, one line below to add one.

Order matters only for ties: where two families propose the same column, the earlier one keeps it
(a named law before a generic power), and the screen's ranking is stable. The names are the
`Effect` literal of schemas/discovery.py (tests/solvers/test_discovery_families.py checks they agree).
"""
from __future__ import annotations

from greyfit.solvers.screening.families.base import Family
from greyfit.solvers.screening.families.coupling import CouplingLaw
from greyfit.solvers.screening.families.custom import Custom
from greyfit.solvers.screening.families.drag import QuadraticDrag
from greyfit.solvers.screening.families.flow import SqrtFlow
from greyfit.solvers.screening.families.friction import Coulomb
from greyfit.solvers.screening.families.input_laws import InputLaw
from greyfit.solvers.screening.families.inputs import DeadZone, InputDelay, Saturation
from greyfit.solvers.screening.families.lags import ExtraPole, InputLag, SensorLag
from greyfit.solvers.screening.families.offsets import Offset
from greyfit.solvers.screening.families.parameter_laws import Arrhenius, ParameterLaw
from greyfit.solvers.screening.families.powers import PowerLaw
from greyfit.solvers.screening.families.radiation import Radiation
from greyfit.solvers.screening.families.rates import SaturableRate
from greyfit.solvers.screening.families.sensor import OutputAbs, OutputGain, OutputOffset, OutputSaturation
from greyfit.solvers.screening.families.stiffness import CubicStiffness
from greyfit.solvers.screening.families.stores import HiddenStore
from greyfit.solvers.screening.families.switching import StateDependent
from greyfit.solvers.screening.families.time_varying import ParameterDrift, ParameterStep

FAMILIES: tuple[Family, ...] = (
    Coulomb(),
    QuadraticDrag(),
    CubicStiffness(),
    CouplingLaw(),
    Offset(),
    SqrtFlow(),
    Radiation(),
    Arrhenius(),
    SaturableRate(),
    Saturation(),
    DeadZone(),
    OutputOffset(),
    OutputGain(),
    OutputAbs(),
    OutputSaturation(),
    PowerLaw(),
    InputLaw(),
    ParameterLaw(),
    ParameterStep(),
    ParameterDrift(),
    StateDependent(),
    InputDelay(),
    SensorLag(),
    InputLag(),
    ExtraPole(),
    HiddenStore(),
)
# the user's candidates: always screened when given, not an entry of `effects`
USER = Custom()

EFFECT_NAMES: tuple[str, ...] = tuple(f.name for f in FAMILIES)
BY_NAME: dict[str, Family] = {f.name: f for f in FAMILIES}

__all__ = ["FAMILIES", "USER", "EFFECT_NAMES", "BY_NAME", "Family"]
