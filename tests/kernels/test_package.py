"""Packaging promises: the kernels import light, the CLI answers --help/--version."""

import subprocess
import sys

import mcgs_warp


def test_kernels_import_pulls_no_heavy_dependencies():
    code = (
        "import sys, mcgs_warp.kernels; "
        "heavy = [m for m in ('cv2', 'scipy', 'pxr', 'yaml') if m in sys.modules]; "
        "print(heavy); sys.exit(1 if heavy else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_cli_version_and_help():
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "--version"], capture_output=True, text=True)
    assert res.returncode == 0 and mcgs_warp.__version__ in res.stdout
    res = subprocess.run([sys.executable, "-m", "mcgs_warp", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "usage: mcgs-slam" in res.stdout
