"""Every import of labcal is at the top of its module, where a reader sees it: a module start-up does
not need is named there as `lazy("...")` (labcal.lazy) with its reason, not imported inside the
function that uses it. The few left in a function are listed here, each with why."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("labcal", "drivers", "sim")  # drivers/ and sim/ are labcal.drivers and labcal.sim

# file -> the modules its function bodies may import, each with why
ALLOWED: dict[str, dict[str, str]] = {
    # The [lab] extra's libraries, each import inside try/except ImportError: the import is the test of
    # whether they are installed, and its failure becomes one line naming `pip install 'labcal[lab]'`.
    "labcal/commands/serve.py": {"labcal.server.serving": "FastAPI and uvicorn, for `labcal serve`"},
    "labcal/commands/user.py": {"labcal.app.labdatabase": "argon2 and SQLAlchemy, for `labcal user`"},
    "labcal/run/notify.py": {"apprise": "the run's notifications"},
    "labcal/store/labdb.py": {"sqlalchemy": "psycopg, which the engine of a lab database on a server loads"},
}
# file -> the modules its function bodies import unguarded, each with why
JUSTIFIED: dict[str, dict[str, str]] = {
    # `labcal.__version__` is read from the installed metadata by the package's module __getattr__
    # when first asked; a name bound at the package's top would be one more attribute of `labcal`
    "labcal/__init__.py": {"importlib.metadata": "read by labcal.__version__ when first asked"},
}


def imported(node: ast.Import | ast.ImportFrom) -> list[str]:
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    return ["." * node.level + (node.module or "")]


def catches_import_error(node: ast.Try) -> bool:
    names = {n.id for h in node.handlers if h.type is not None
             for n in ast.walk(h.type) if isinstance(n, ast.Name)}
    return bool(names & {"ImportError", "ModuleNotFoundError"})


def function_body_imports(tree: ast.Module) -> list[tuple[int, str, bool]]:
    """(line, module, whether a try/except ImportError holds it) of each import inside a function."""
    found = []

    def visit(node: ast.AST, in_function: bool, guarded: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import | ast.ImportFrom):
                if in_function:
                    found.extend((child.lineno, name, guarded) for name in imported(child))
            elif isinstance(child, ast.Try) and catches_import_error(child):
                for part in child.body:
                    visit(ast.Module([part], []), in_function, True)
                for part in (*child.handlers, *child.orelse, *child.finalbody):
                    visit(ast.Module([part], []), in_function, guarded)
            else:
                function = isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
                visit(child, in_function or function, guarded)

    visit(tree, False, False)
    return found


def imports_in_functions_of(name: str) -> list[tuple[int, str, bool]]:
    return function_body_imports(ast.parse((ROOT / name).read_text(encoding="utf-8")))


def modules() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def test_no_module_imports_inside_a_function_but_the_optional_extras_and_the_few_justified():
    hidden = []
    for path in modules():
        name = path.relative_to(ROOT).as_posix()
        allowed = ALLOWED.get(name, {})
        for line, module, guarded in imports_in_functions_of(name):
            if (module not in allowed or not guarded) and module not in JUSTIFIED.get(name, {}):
                hidden.append(f"{name}:{line}: import of {module}")
    assert not hidden, ("imports inside functions (name the module at the top with labcal.lazy.lazy, "
                        "or list an optional extra here with why):\n" + "\n".join(hidden))


def test_each_allowed_import_is_still_there():
    """An entry left after its import went would allow the next one unseen."""
    for name, allowed in (*ALLOWED.items(), *JUSTIFIED.items()):
        found = {module for _, module, _ in imports_in_functions_of(name)}
        assert set(allowed) <= found, f"{name}: {sorted(set(allowed) - found)} is imported in no function now"


def test_the_check_sees_an_import_in_a_nested_function_and_in_a_method():
    source = ("import os\n"
              "def f():\n    def g():\n        import json\n    return g\n"
              "class C:\n    def m(self):\n        from labcal.store import labdb\n"
              "if True:\n    import sys\n"
              "def h():\n    try:\n        import apprise\n    except ImportError:\n        import csv\n")
    assert function_body_imports(ast.parse(source)) == [
        (4, "json", False), (8, "labcal.store", False), (13, "apprise", True), (15, "csv", False)]
