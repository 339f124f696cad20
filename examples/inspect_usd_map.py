"""Open a run's USD map and print its prims and splat attributes.

    python examples/inspect_usd_map.py out/synthetic/run/map.usdc
"""

import sys

import numpy as np
from pxr import Usd, UsdVol


def describe(path: str) -> str:
    stage = Usd.Stage.Open(path)
    lines = [f"{path}: up axis {Usd.Stage.Open(path).GetMetadata('upAxis')}, default prim {stage.GetDefaultPrim().GetPath()}"]
    for prim in stage.Traverse():
        lines.append(f"  {prim.GetPath()}  ({prim.GetTypeName()})")
        if prim.IsA(UsdVol.ParticleField3DGaussianSplat):
            splat = UsdVol.ParticleField3DGaussianSplat(prim)
            pos = np.array(splat.GetPositionsAttr().Get())
            opa = np.array(splat.GetOpacitiesAttr().Get())
            sca = np.array(splat.GetScalesAttr().Get())
            lines.append(f"    {len(pos)} Gaussians; extent {np.array(splat.GetExtentAttr().Get()).round(2).tolist()}")
            lines.append(f"    opacity median {np.median(opa):.3f}; scale median {np.median(sca):.4f} m; SH degree {splat.GetRadianceSphericalHarmonicsDegreeAttr().Get()}")
    return "\n".join(lines)


if __name__ == "__main__":
    print(describe(sys.argv[1] if len(sys.argv) > 1 else "out/synthetic/run/map.usdc"))
