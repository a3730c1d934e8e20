"""Every public function of solvers/ has a numpydoc docstring that documents each of its arguments
(python-control checks its public functions the same way): the docs site renders them, and a
parameter nobody described is one a user has to guess."""
import ast
import re
from pathlib import Path

SOLVERS = Path(__file__).resolve().parents[2] / "solvers"


def undocumented() -> list[str]:
    out = []
    for path in sorted(SOLVERS.rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if not isinstance(node, ast.FunctionDef) or node.name.startswith("_"):
                continue
            args = [a.arg for a in node.args.args + node.args.kwonlyargs if a.arg not in ("self", "cls")]
            doc = ast.get_docstring(node) or ""
            where = f"{path.relative_to(SOLVERS.parent)}:{node.lineno} {node.name}"
            if not args:
                if not doc:
                    out.append(f"{where}: no docstring")
                continue
            section = re.search(r"^Parameters\n-+\n(.*?)(?:^\S[^\n]*\n-+\n|\Z)", doc, re.S | re.M)
            if section is None:
                out.append(f"{where}: no Parameters section")
                continue
            # an entry starts at the left margin: "name : type", or several names "a, b : type" / "a, b"
            named = {n.strip().lstrip("*") for line in section.group(1).splitlines()
                     if line and not line[0].isspace() for n in line.split(" : ")[0].split(",")}
            missing = [a for a in args if a not in named]
            if missing:
                out.append(f"{where}: {', '.join(missing)} not described")
    return out


def test_every_public_solver_function_documents_its_arguments():
    missing = undocumented()
    assert not missing, f"{len(missing)} functions:\n" + "\n".join(missing)
