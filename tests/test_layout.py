"""The code's folders are floors: a module imports only from its own floor or below, and nothing imports in a circle.

Every module of ``fastmesh``, ``fastmesh_jobs``, ``service`` and ``worker`` is parsed (``ast``, no import runs) and
each import it writes, at the top or inside a function, becomes an edge to the module it names.  Three rules:

1. No circle between modules.
2. No circle between units: a unit is one row of ``FLOORS`` (a folder, or a module loose at the top of
   ``fastmesh``), so two folders never lean on each other even through different modules.
3. No upward import: a module's unit sits on a floor at least as high as the unit it imports from.

Plus one rule of the product: ``service`` and ``worker`` share the job system through ``fastmesh_jobs`` and never
import each other.  And one of size: a module of ``fastmesh`` stays under ``MAX_MODULE_LINES`` lines and a
function under ``MAX_FUNCTION_LINES``, but for those ``LONG`` names (a list that only shrinks).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fastmesh", "fastmesh_jobs", "service", "worker")

# The floors, lowest first: floor -> the units on it and the step of the method (or the layer) they are.
FLOORS: dict[int, dict[str, str]] = {
    0: {"fastmesh.tokenizer": "the 7-bit grid and the token languages",
        "fastmesh.params": "the generation parameters and their bounds",
        "fastmesh.progress": "a job's stages and fraction done"},
    1: {"fastmesh.shapes": "step 1: the shape type; loading, checking and sampling inputs; their frame and planes"},
    2: {"fastmesh.faces": "steps 5-9: faces from vertices and edges, holes, closure, the face count"},
    3: {"fastmesh.models": "steps 2-4: the networks",
        "fastmesh.fitting": "step 3: decoded vertices fitted to the input's planes",
        "fastmesh.export": "the result as written: files, quads, UV layout, baked texture, placement",
        "fastmesh.preview": "images of a mesh",
        "fastmesh.remote": "the HTTP client and the load tester"},
    4: {"fastmesh.evaluation": "measures: distances, quality report, primitives, evaluation runs",
        "fastmesh.batch": "several jobs' vertex decoding as one batch",
        "fastmesh.request": "one request's input, frames, samples and decisions, made once per job"},
    5: {"fastmesh.pipeline": "the steps in order",
        "fastmesh.training": "the training loop, its data and one task per network"},
    6: {"fastmesh.cli": "the command line"},
    7: {"fastmesh_jobs": "the job system the service and the workers share: store, reaper, settings, runtime"},
    8: {"service": "the HTTP service", "worker": "the RQ workers"},
}
APART = [("service", "worker")]  # units that never import each other
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60
# Modules ("path") and functions ("path:name") of fastmesh allowed over the limits; remove a row once it fits.
LONG: set[str] = set()


def modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of ``PACKAGES`` (a package as its ``__init__``)."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _import_nodes(name: str, path: Path):
    """Each import statement of the module ``name`` (file ``path``), anywhere in its body, with the absolute module
    a ``from`` import names (relative ones resolved against the module's package; None for a plain ``import``)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield node, None
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            yield node, base


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The modules of ``known`` that the module ``name`` (file ``path``) imports, anywhere in its body."""
    out = set()
    for node, base in _import_nodes(name, path):
        if base is None:
            targets = [a.name for a in node.names]
        else:  # ``from a import b`` names the module a.b where there is one, else a name inside a
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        for target in targets:
            while target and target not in known:  # ``import a.b.c`` of a name inside a.b
                target = target.rpartition(".")[0]
            if target and target != name:
                out.add(target)
    return out


def unresolved(name: str, path: Path, known: set[str]) -> list[str]:
    """The imports of ``name`` that name a module of ``PACKAGES`` this tree does not have.

    ``fastmesh`` is a namespace package: an installed copy elsewhere on the path would still answer such an
    import at run time, so the tree is checked on its own."""
    out = []
    for node, base in _import_nodes(name, path):
        if base is None:
            bases = [a.name for a in node.names]
        else:
            bases = [f"{base}.{a.name}" if base in PACKAGES else base for a in node.names]
        out += [f"{name}:{node.lineno} {b}" for b in bases
                if b.split(".")[0] in PACKAGES and b not in PACKAGES and b not in known]
    return out


def graph() -> dict[str, set[str]]:
    found = modules()
    return {name: imports(name, path, set(found)) for name, path in found.items()}


def unit_of(name: str) -> str | None:
    """The row of ``FLOORS`` a module belongs to: the longest unit that is the module or a package above it."""
    units = [u for floor in FLOORS.values() for u in floor if name == u or name.startswith(u + ".")]
    return max(units, key=len) if units else None


def floor_of(unit: str) -> int:
    return next(f for f, units in FLOORS.items() if unit in units)


def circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan's algorithm, iterative)."""
    index, low, on, stack, found, counter = {}, {}, set(), [], [], [0]

    def visit(root: str) -> None:
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        top = stack.pop()
                        on.discard(top)
                        component.append(top)
                        if top == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
            elif child not in index:
                index[child] = low[child] = counter[0]
                counter[0] += 1
                stack.append(child)
                on.add(child)
                work.append((child, iter(sorted(edges.get(child, ())))))
            elif child in on:
                low[node] = min(low[node], index[child])

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return found


def test_every_module_has_a_floor():
    assert [name for name in modules() if unit_of(name) is None] == []


def test_every_import_names_a_module_of_this_tree():
    """In the packages, the tests, the benchmarks and the scripts."""
    found = modules()
    scripts = {".".join(p.relative_to(ROOT).with_suffix("").parts): p
               for folder in ("tests", "benchmarks", "scripts") for p in sorted((ROOT / folder).rglob("*.py"))}
    assert [u for name, path in (found | scripts).items() for u in unresolved(name, path, set(found))] == []


def test_no_circle_between_modules():
    assert circles(graph()) == []


def test_no_circle_between_units():
    units: dict[str, set[str]] = {}
    for name, targets in graph().items():
        here = unit_of(name)
        if here is not None:
            units.setdefault(here, set()).update(unit_of(t) for t in targets if unit_of(t) not in (here, None))
    assert circles(units) == []


def test_no_import_points_up():
    upward = [f"{name} (floor {floor_of(unit_of(name))}) imports {target} (floor {floor_of(unit_of(target))})"
              for name, targets in graph().items() if unit_of(name)
              for target in sorted(targets) if unit_of(target)
              and floor_of(unit_of(target)) > floor_of(unit_of(name))]
    assert upward == []


def test_service_and_worker_share_only_the_job_system():
    crossing = [f"{name} imports {target}" for name, targets in graph().items() for target in sorted(targets)
                for a, b in APART if {unit_of(name), unit_of(target)} == {a, b}]
    assert crossing == []


def long_code(package: str = "fastmesh") -> set[str]:
    """The modules of ``package`` over ``MAX_MODULE_LINES`` lines and its functions (methods and nested ones
    too) over ``MAX_FUNCTION_LINES``, a function's lines counted from its ``def`` to its last line."""
    found = set()
    for path in sorted((ROOT / package).rglob("*.py")):
        name, text = str(path.relative_to(ROOT)), path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            found.add(name)
        for node in ast.walk(ast.parse(text, name)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and (
                    node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES):
                found.add(f"{name}:{node.name}")
    return found


def test_modules_and_functions_are_short():
    assert long_code() - LONG == set()


def test_the_long_list_only_names_what_is_still_long():
    assert LONG - long_code() == set()


def test_the_rules_see_a_circle_and_an_upward_import():
    """The checks themselves: a made-up circle and a made-up upward import are found."""
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert floor_of(unit_of("fastmesh.shapes.io")) < floor_of(unit_of("fastmesh.pipeline"))
    assert unit_of("fastmesh.faces.holes") == "fastmesh.faces" and unit_of("fastmesh_jobs.store") == "fastmesh_jobs"
