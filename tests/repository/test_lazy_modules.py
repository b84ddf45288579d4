"""labcal.lazy: a module named at the top of another is imported at its first use, and is then the
ordinary module (each check in a fresh interpreter, so that what an earlier test imported does not
count)."""

from __future__ import annotations

import subprocess
import sys


def run(code: str) -> str:
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_a_lazy_module_is_imported_at_its_first_attribute_access_and_not_before():
    # colorsys: a standard-library module nothing in labcal.lazy or the interpreter's start imports
    out = run("import sys\nfrom labcal.lazy import lazy\n"
              "colorsys = lazy('colorsys')\nprint('colorsys' in sys.modules)\n"
              "print(colorsys.rgb_to_hsv(1.0, 0.0, 0.0))\nprint('colorsys' in sys.modules)")
    # pure red: hue 0, full saturation, full value
    assert out.splitlines() == ["False", "(0.0, 1.0, 1.0)", "True"]


def test_a_lazy_submodule_imports_neither_it_nor_its_parent_package_before_its_first_use():
    out = run("import sys\nfrom labcal.lazy import lazy\n"
              "parsers = lazy('email.parser')\nprint('email' in sys.modules, 'email.parser' in sys.modules)\n"
              "parsers.Parser\nprint('email' in sys.modules, 'email.parser' in sys.modules)")
    assert out.splitlines() == ["False False", "True True"]


def test_an_attribute_replaced_on_the_real_module_is_the_one_the_lazy_module_gives():
    """As a test's monkeypatch.setattr(module, ...) replaces it: the stand-in forwards, never copies."""
    out = run("import colorsys\nfrom labcal.lazy import lazy\n"
              "deferred = lazy('colorsys')\nfirst = deferred.rgb_to_hsv\n"
              "colorsys.rgb_to_hsv = lambda *a: 'replaced'\nprint(deferred.rgb_to_hsv(1, 0, 0))\n"
              "print(first is not colorsys.rgb_to_hsv)")
    assert out.splitlines() == ["replaced", "True"]


def test_a_missing_module_fails_at_its_first_use_with_the_import_error():
    out = run("from labcal.lazy import lazy\nmissing = lazy('labcal.no_such_module')\nprint('made')\n"
              "try:\n    missing.anything\nexcept ModuleNotFoundError as e:\n    print(e.name)")
    assert out.splitlines() == ["made", "labcal.no_such_module"]


def test_a_missing_attribute_is_an_attribute_error_naming_the_module():
    out = run("from labcal.lazy import lazy\ncolorsys = lazy('colorsys')\n"
              "try:\n    colorsys.no_such_function\nexcept AttributeError as e:\n    print(e)")
    assert "colorsys" in out and "no_such_function" in out
