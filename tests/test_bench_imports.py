"""bench/ imports the shared fixture modules of tests/ (systems, servers, records), never a test module:
a benchmark that imports `tests.test_*` breaks when a test is renamed or split, and runs its
module-level setup."""
import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEST_MODULE = re.compile(r"^tests(\.\w+)*\.test_\w*")


def imported_modules(tree: ast.Module) -> list[str]:
    """Every module an import statement anywhere in `tree` names (`from a import b` gives a.b too,
    since b may be a module), and dotted string constants naming a module under tests (importlib,
    patch targets)."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append(node.module)
            out += [f"{node.module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith("tests."):
            out.append(node.value)
    return out


def test_imported_modules_sees_each_way_of_naming_a_test_module():
    tree = ast.parse("import tests.test_a\nfrom tests.solvers.test_b import f\nfrom tests import test_c\n"
                     "def g():\n    from tests.service import test_d\n"
                     "importlib.import_module('tests.test_e')\nfrom tests.systems import msd_model\n")
    found = {m for m in imported_modules(tree) if TEST_MODULE.match(m)}
    assert found == {"tests.test_a", "tests.solvers.test_b", "tests.solvers.test_b.f", "tests.test_c",
                     "tests.service.test_d", "tests.test_e"}
    assert not any(TEST_MODULE.match(m) for m in ("tests.systems", "tests.systems.msd_model", "tests.servers"))


def test_bench_imports_no_test_module():
    scripts = sorted((ROOT / "bench").rglob("*.py"))
    assert scripts
    found = [f"{path.relative_to(ROOT)}: {module}" for path in scripts
             for module in imported_modules(ast.parse(path.read_text())) if TEST_MODULE.match(module)]
    assert not found, "bench/ imports test modules (move what it needs into a fixture module):\n" + "\n".join(found)
