"""Every public function of solvers/, and every public method of its public classes, has a numpydoc
docstring that documents each of its arguments and, when it returns something, what it returns
(python-control checks its public functions the same way): the docs site renders them, and a
parameter or a result nobody described is one a user has to guess."""
import ast
import re
from pathlib import Path

SOLVERS = Path(__file__).resolve().parents[2] / "solvers"
SECTION = r"^{}\n-+\n(.*?)(?:^\S[^\n]*\n-+\n|\Z)"


def public_functions(tree: ast.Module):
    """(name, node) of the module's public functions and of its public classes' public methods."""
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and not node.name.startswith("_"):
            yield node.name, node
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for member in node.body:
                if isinstance(member, ast.FunctionDef) and not member.name.startswith("_"):
                    yield f"{node.name}.{member.name}", member


def _own_nodes(fn: ast.FunctionDef):
    """The nodes of `fn`'s body, not those of the functions and classes defined inside it."""
    stack = list(fn.body)
    while stack:
        node = stack.pop()
        yield node
        stack += [c for c in ast.iter_child_nodes(node)
                  if not isinstance(c, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef))]


def _is_none(node) -> bool:
    return isinstance(node, ast.Constant) and node.value is None


def returns_something(fn: ast.FunctionDef) -> bool:
    """Annotated with a type other than None, or (unannotated) a `return` of something not None."""
    if fn.returns is not None:
        return not _is_none(fn.returns)
    return any(isinstance(n, ast.Return) and n.value is not None and not _is_none(n.value) for n in _own_nodes(fn))


def problems(tree: ast.Module) -> list[str]:
    """What the module's public functions and methods leave undocumented, one line each."""
    out = []
    for name, node in public_functions(tree):
        args = [a.arg for a in node.args.posonlyargs + node.args.args + node.args.kwonlyargs
                if a.arg not in ("self", "cls")]
        doc = ast.get_docstring(node) or ""
        where = f"{node.lineno} {name}"
        if not doc:
            out.append(f"{where}: no docstring")
            continue
        if returns_something(node) and not re.search(r"^(Returns|Yields)\n-+\n", doc, re.M):
            out.append(f"{where}: returns something, no Returns section")
        if not args:
            continue
        section = re.search(SECTION.format("Parameters"), doc, re.S | re.M)
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


def undocumented() -> list[str]:
    return [f"{path.relative_to(SOLVERS.parent)}:{problem}" for path in sorted(SOLVERS.rglob("*.py"))
            for problem in problems(ast.parse(path.read_text()))]


def test_every_public_solver_function_and_method_documents_its_arguments_and_result():
    missing = undocumented()
    assert not missing, f"{len(missing)} functions:\n" + "\n".join(missing)


def test_the_check_sees_methods_and_results():
    # a test that cannot fail is a defect: the rules above catch what they exist for
    tree = ast.parse('''
class Public:
    def method(self, x):
        """One line."""
        return x

    def _private(self, y):
        return y


def plain(a) -> int:
    """One line.

    Parameters
    ----------
    a : int
        A.

    Returns
    -------
    int
        A.
    """
    return a


def nothing(a) -> None:
    """One line.

    Parameters
    ----------
    a : int
        A.
    """
''')
    assert problems(tree) == ["3 Public.method: returns something, no Returns section",
                              "3 Public.method: no Parameters section"]
    names = dict(public_functions(tree))
    assert set(names) == {"Public.method", "plain", "nothing"}
    assert returns_something(names["plain"]) and not returns_something(names["nothing"])
