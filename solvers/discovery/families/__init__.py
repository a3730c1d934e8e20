"""The effect library as a registry of families: one module per family, one line below to add one.

Order matters only for ties: where two families propose the same column, the earlier one keeps it
(a named law before a generic power), and the screen's ranking is stable. The names are the
`Effect` literal of schemas/discovery.py (tests/solvers/test_discovery_families.py checks they agree).
"""
from __future__ import annotations

from greyfit.solvers.discovery.families.base import Family
from greyfit.solvers.discovery.families.coupling import CouplingLaw
from greyfit.solvers.discovery.families.custom import Custom
from greyfit.solvers.discovery.families.drag import QuadraticDrag
from greyfit.solvers.discovery.families.flow import SqrtFlow
from greyfit.solvers.discovery.families.friction import Coulomb
from greyfit.solvers.discovery.families.input_laws import InputLaw
from greyfit.solvers.discovery.families.inputs import DeadZone, InputDelay, Saturation
from greyfit.solvers.discovery.families.lags import ExtraPole, InputLag, SensorLag
from greyfit.solvers.discovery.families.offsets import Offset
from greyfit.solvers.discovery.families.parameter_laws import Arrhenius, ParameterLaw
from greyfit.solvers.discovery.families.powers import PowerLaw
from greyfit.solvers.discovery.families.radiation import Radiation
from greyfit.solvers.discovery.families.rates import SaturableRate
from greyfit.solvers.discovery.families.sensor import OutputAbs, OutputGain, OutputOffset, OutputSaturation
from greyfit.solvers.discovery.families.stiffness import CubicStiffness
from greyfit.solvers.discovery.families.stores import HiddenStore
from greyfit.solvers.discovery.families.switching import StateDependent
from greyfit.solvers.discovery.families.time_varying import ParameterDrift, ParameterStep

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
