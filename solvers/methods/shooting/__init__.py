"""Output error by shooting, split by role.

- `model.py`: the output-error model (compiled step, simulation, sensitivities) every form shares;
- `single.py`: single shooting; `multiple.py`: multiple shooting (nodes and gap constraints);
- `structured.py`: the same NLPs evaluated from compiled per-sample blocks where the problem allows;
- `curvature.py`: the gaps' curvature for the Gauss-Newton Hessian of multiple shooting;
- `hybrid.py`: the solver that uses it, and `make_solver`, the one place a fit's solver is chosen.
"""
from greyfit.solvers.methods.shooting.model import OutputErrorModel, sensitivity_jacobian
from greyfit.solvers.methods.shooting.multiple import build_multiple_shooting
from greyfit.solvers.methods.shooting.single import build_single_shooting

__all__ = ["OutputErrorModel", "sensitivity_jacobian", "build_single_shooting", "build_multiple_shooting"]
