"""Every benchmark script starts as its docstring says (``python benchmarks/<name>.py``): it
imports (no file in benchmarks/ shadows a module of the standard library or a dependency, as
a ``profile.py`` there once shadowed the one cProfile imports) and parses its arguments."""

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = sorted((Path(__file__).resolve().parents[2] / "benchmarks").glob("*.py"))


def test_no_benchmark_shadows_a_module_it_imports():
    import importlib.util

    shadowing = [p.name for p in BENCHMARKS if p.stem in sys.stdlib_module_names or importlib.util.find_spec(p.stem) is not None]  # (run from the repository root: benchmarks/ is not on the path)
    assert not shadowing, shadowing


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.stem)
def test_benchmark_prints_its_usage(script):
    res = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and "usage" in res.stdout, res.stderr[-2000:]
