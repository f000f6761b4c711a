"""The package's shape (issue 52): stage subpackages, few modules at the top, short modules and
functions, and the old flat module names still importing as the very same modules."""

import ast
import subprocess
import sys
from pathlib import Path

import mjxdiff

ROOT = Path(mjxdiff.__file__).parent
STAGES = ("input", "engine", "compare", "runner", "output", "tools")


def _modules() -> dict[str, Path]:
    return {".".join(p.relative_to(ROOT).with_suffix("").parts): p for p in ROOT.rglob("*.py")
            if "_scenarios" not in p.parts}


def test_the_top_level_holds_at_most_12_modules_and_one_folder_per_stage():
    top = sorted(p.stem for p in ROOT.glob("*.py"))
    assert len(top) <= 12, top
    assert all((ROOT / s / "__init__.py").is_file() and (ROOT / s / "__init__.py").read_text().startswith('"""')
               for s in STAGES)


def test_no_module_is_over_700_lines_and_no_function_over_80():
    long_modules, long_functions = [], []
    for name, path in _modules().items():
        text = path.read_text()
        if len(text.splitlines()) > 700:
            long_modules.append((name, len(text.splitlines())))
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 80:
                long_functions.append((name, node.name, node.end_lineno - node.lineno + 1))
    assert long_modules == [] and long_functions == [], (long_modules, long_functions)


def test_the_old_flat_names_import_the_moved_modules_themselves():
    """``import mjxdiff.sweep`` and ``from mjxdiff.scenario import ...`` keep working for this
    release, and give the module object of the new path (one module under two names: a patch
    through either reaches the code)."""
    assert all((ROOT / stage / f"{name}.py").is_file() for name, stage in mjxdiff._MOVED.items())
    code = ("import mjxdiff, importlib; "
            "assert all(importlib.import_module(f'mjxdiff.{m}') is importlib.import_module(f'mjxdiff.{s}.{m}') "
            "for m, s in mjxdiff._MOVED.items()); "
            "from mjxdiff.scenario import load_scenario; from mjxdiff.input.scenario import load_scenario as l2; "
            "assert load_scenario is l2")
    subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)


def test_mjxdiff_sweep_is_one_thing():
    code = "import mjxdiff; f = mjxdiff.sweep; mjxdiff.SweepConfig; assert mjxdiff.sweep is f"
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
