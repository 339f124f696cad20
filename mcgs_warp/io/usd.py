"""OpenUSD export: the map as ``UsdVol.ParticleField3DGaussianSplat`` (usd-core >= 26.3)
and the keyframe cameras as ``UsdGeom.Camera``.

The prim takes activated values (DESIGN.md): ``positions`` (world, m),
``orientations`` (quatf, real part first), ``scales`` (linear), ``opacities`` in
[0, 1], and colour as degree-0 spherical harmonics with DC = (rgb - 0.5) / 0.28209479.
``primvars:measured`` (bool per splat, vertex interpolation) says which splats were placed at
a measured depth, the others at a guessed one (mapping/gaussian_map.py).
The stage is written to a temporary file and renamed (atomic).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from .ply import SH_C0

MAP_PATH = "/World/Map"
CAMERAS_PATH = "/World/Keyframes"


def valid_identifier(name: str) -> str:
    """A USD prim name from any string (letters, digits, underscores; not starting with a digit)."""
    import re

    ident = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return ident if ident and not ident[0].isdigit() else f"_{ident}"


def write_usd(path, params: dict, cameras=None) -> None:
    """``params``: map arrays (``means``, ``quats`` xyzw, ``log_scales``, ``opacity_logits``,
    ``colors``; optional ``measured`` [N] bool); ``cameras``: optional list of ``(name, T_w_c [4,4], CameraSpec)``."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdVol, Vt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    os.unlink(tmp)  # USD creates the file itself
    try:
        stage = Usd.Stage.CreateNew(tmp)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        world = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(world.GetPrim())
        splat = UsdVol.ParticleField3DGaussianSplat.Define(stage, MAP_PATH)
        means = np.asarray(params["means"], np.float32)
        q = np.asarray(params["quats"], np.float64)
        q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
        scales = np.exp(np.asarray(params["log_scales"], np.float64)).astype(np.float32)
        opac = (1.0 / (1.0 + np.exp(-np.asarray(params["opacity_logits"], np.float64)))).astype(np.float32)
        dc = ((np.asarray(params["colors"], np.float64) - 0.5) / SH_C0).astype(np.float32)
        splat.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(means))
        splat.CreateOrientationsAttr(Vt.QuatfArray([Gf.Quatf(float(w), float(x), float(y), float(z)) for x, y, z, w in q]))
        splat.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(scales))
        splat.CreateOpacitiesAttr(Vt.FloatArray.FromNumpy(opac))
        splat.CreateRadianceSphericalHarmonicsDegreeAttr(0)
        splat.CreateRadianceSphericalHarmonicsCoefficientsAttr(Vt.Vec3fArray.FromNumpy(dc))
        if params.get("measured") is not None:
            pv = UsdGeom.PrimvarsAPI(splat.GetPrim()).CreatePrimvar("measured", Sdf.ValueTypeNames.BoolArray, UsdGeom.Tokens.vertex)
            pv.Set(Vt.BoolArray([bool(m) for m in np.asarray(params["measured"], bool)]))
        if len(means):
            lo = (means - 3 * scales.max(1, keepdims=True)).min(0)
            hi = (means + 3 * scales.max(1, keepdims=True)).max(0)
            splat.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        for name, T_w_c, spec in cameras or []:
            cam = UsdGeom.Camera.Define(stage, f"{CAMERAS_PATH}/{valid_identifier(name)}")
            # USD cameras look down -Z with +Y up; ours look down +Z with +Y down.
            flip = np.diag([1.0, -1.0, -1.0, 1.0])
            M = (np.asarray(T_w_c) @ flip).T  # USD uses row vectors
            cam.AddTransformOp().Set(Gf.Matrix4d(M.tolist()))
            if spec.intrinsics is not None:
                fx = spec.intrinsics[0]
                aperture = 20.955  # mm, USD's default horizontal aperture
                cam.CreateHorizontalApertureAttr(aperture)
                cam.CreateVerticalApertureAttr(aperture * spec.height / spec.width)
                cam.CreateFocalLengthAttr(aperture * fx / spec.width)
            cam.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
        stage.GetRootLayer().Save()
        del stage
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def read_usd_map(path) -> dict:
    """Activated splat attributes of the map prim (for checks and viewers)."""
    from pxr import Usd, UsdGeom, UsdVol

    stage = Usd.Stage.Open(str(path))
    splat = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath(MAP_PATH))
    q = splat.GetOrientationsAttr().Get()
    return {
        "positions": np.array(splat.GetPositionsAttr().Get(), np.float32).reshape(-1, 3),
        "orientations_wxyz": np.array([[x.GetReal(), *x.GetImaginary()] for x in q], np.float32).reshape(-1, 4),
        "scales": np.array(splat.GetScalesAttr().Get(), np.float32).reshape(-1, 3),
        "opacities": np.array(splat.GetOpacitiesAttr().Get(), np.float32),
        "sh_degree": splat.GetRadianceSphericalHarmonicsDegreeAttr().Get(),
        "sh_coefficients": np.array(splat.GetRadianceSphericalHarmonicsCoefficientsAttr().Get(), np.float32).reshape(-1, 3),
        "extent": np.array(splat.GetExtentAttr().Get(), np.float32),
        "cameras": [p.GetName() for p in stage.Traverse() if p.GetTypeName() == "Camera"],
        "measured": np.array(pv.Get(), bool) if (pv := UsdGeom.PrimvarsAPI(splat.GetPrim()).GetPrimvar("measured")) and pv.HasValue() else None,
    }
