"""Every public function of solvers/, and every public method of its public classes, has a numpydoc
docstring that documents each of its arguments and, when it returns something, what it returns
(python-control checks its public functions the same way): the docs site renders them, and a
parameter or a result nobody described is one a user has to guess.

A method that implements a documented method of a base class or of a Protocol inherits its sections
(python-control's docstrings_test.py skips inherited docstrings the same way): when the base's method
is fully documented, takes the same arguments, and the implementation's own docstring is a summary
without sections (a line on what this implementation does), its sections are not asked for again. The Protocol is found
structurally, as the type checker finds it: a Protocol of solvers/ whose every member the class has."""
import ast
import re
from pathlib import Path
from typing import NamedTuple

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


def _args(node: ast.FunctionDef) -> list[str]:
    return [a.arg for a in node.args.posonlyargs + node.args.args + node.args.kwonlyargs
            if a.arg not in ("self", "cls")]


def _base_name(node: ast.expr) -> str:
    """`Base`, `module.Base` and `Base[T]` all name Base."""
    if isinstance(node, ast.Subscript):
        node = node.value
    return node.attr if isinstance(node, ast.Attribute) else getattr(node, "id", "")


class ClassInfo(NamedTuple):
    bases: list[str]
    protocol: bool
    methods: dict[str, ast.FunctionDef]
    members: set[str]   # methods, properties, class attributes and those a method sets on self


def class_index(trees) -> dict[str, ClassInfo]:
    """Every top-level class of the modules by name: its bases' names, whether it is a Protocol, its methods."""
    index = {}
    for tree in trees:
        for node in tree.body:
            if not isinstance(node, ast.ClassDef):
                continue
            bases = [_base_name(b) for b in node.bases]
            methods = {m.name: m for m in node.body if isinstance(m, ast.FunctionDef)}
            members = set(methods) | {t.id for m in node.body if isinstance(m, (ast.AnnAssign, ast.Assign))
                                      for t in (m.targets if isinstance(m, ast.Assign) else [m.target])
                                      if isinstance(t, ast.Name)}
            members |= {n.attr for m in methods.values() for n in ast.walk(m)   # self.x = ... in a method
                        if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store)
                        and isinstance(n.value, ast.Name) and n.value.id == "self"}
            index[node.name] = ClassInfo([b for b in bases if b != "Protocol"], "Protocol" in bases, methods, members)
    return index


def _all_members(name: str, classes: dict[str, ClassInfo], seen=()) -> set[str]:
    info = classes.get(name)
    if info is None or name in seen:
        return set()
    return info.members.union(*(_all_members(b, classes, (*seen, name)) for b in info.bases))


def _documented_parent(cls: str, method: str, classes: dict[str, ClassInfo], seen=()):
    """The fully documented method `method` of a base class of `cls` (explicit, recursively) or of a
    Protocol that `cls` implements (it has every public member of the Protocol); None if there is none."""
    info = classes.get(cls)
    if info is None or cls in seen:
        return None
    for base in info.bases:
        parent = classes.get(base)
        if parent is not None and method in parent.methods and not _own_problems(parent.methods[method]):
            return parent.methods[method]
        found = _documented_parent(base, method, classes, (*seen, cls))
        if found is not None:
            return found
    have = _all_members(cls, classes)
    for name, proto in classes.items():
        if proto.protocol and name != cls and method in proto.methods and not _own_problems(proto.methods[method]):
            if {m for m in _all_members(name, classes) if not m.startswith("_")} <= have:
                return proto.methods[method]
    return None


def _inherits_its_docstring(cls: str, node: ast.FunctionDef, classes: dict[str, ClassInfo]) -> bool:
    """The method implements a fully documented method with the same arguments and adds no sections."""
    doc = ast.get_docstring(node) or ""
    if not doc or re.search(r"^\S[^\n]*\n-+\n", doc, re.M):   # a line of its own; its sections: checked
        return False
    parent = _documented_parent(cls, node.name, classes)
    return parent is not None and _args(parent) == _args(node)


def problems(tree: ast.Module, classes: dict[str, ClassInfo] | None = None) -> list[str]:
    """What the module's public functions and methods leave undocumented, one line each.

    `classes` (from `class_index` over every module) lets a method inherit a base's or a Protocol's
    sections; without it each method is checked alone."""
    classes = class_index([tree]) if classes is None else classes
    out = []
    for name, node in public_functions(tree):
        owner = name.split(".")[0] if "." in name else None
        if owner is not None and _inherits_its_docstring(owner, node, classes):
            continue
        out += [f"{node.lineno} {name}: {p}" for p in _own_problems(node)]
    return out


def _own_problems(node: ast.FunctionDef) -> list[str]:
    """What the function's own docstring leaves undocumented."""
    args, doc = _args(node), ast.get_docstring(node) or ""
    if not doc:
        return ["no docstring"]
    out = []
    if returns_something(node) and not re.search(r"^(Returns|Yields)\n-+\n", doc, re.M):
        out.append("returns something, no Returns section")
    if not args:
        return out
    section = re.search(SECTION.format("Parameters"), doc, re.S | re.M)
    if section is None:
        return out + ["no Parameters section"]
    # an entry starts at the left margin: "name : type", or several names "a, b : type" / "a, b"
    named = {n.strip().lstrip("*") for line in section.group(1).splitlines()
             if line and not line[0].isspace() for n in line.split(" : ")[0].split(",")}
    missing = [a for a in args if a not in named]
    return out + ([f"{', '.join(missing)} not described"] if missing else [])


def undocumented() -> list[str]:
    trees = {path: ast.parse(path.read_text()) for path in sorted(SOLVERS.rglob("*.py"))}
    classes = class_index(trees.values())
    return [f"{path.relative_to(SOLVERS.parent)}:{problem}" for path, tree in trees.items()
            for problem in problems(tree, classes)]


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


AREA_DOC = '"""The area.\n\nParameters\n----------\nscale : float\n    A factor.\n\n' \
           'Returns\n-------\nfloat\n    The area.\n"""'


def test_an_implementation_inherits_the_sections_of_a_documented_base_or_protocol():
    tree = ast.parse(f'''
class Shape(Protocol):
    def area(self, scale) -> float:
        {AREA_DOC}
        ...


class Square:
    def area(self, scale) -> float:
        """The side squared, times the scale."""
        return scale


class Circle:
    def area(self, factor) -> float:
        """Different arguments: its own sections are asked for."""
        return factor

    def area_again(self, scale) -> float:
        return scale


class Tile(Square):
    def area(self, scale) -> float:
        """A Square, and so a Shape too."""
        return scale


class Base:
    def area(self, scale) -> float:
        {AREA_DOC}
        return scale


class Child(Base):
    def area(self, scale) -> float:
        """Inherited from an explicit base."""
        return scale


class Undocumented(Base):
    def area(self, scale) -> float:
        return scale
''')
    assert problems(tree) == [
        "26 Circle.area: returns something, no Returns section", "26 Circle.area: no Parameters section",
        "30 Circle.area_again: no docstring", "64 Undocumented.area: no docstring"]
