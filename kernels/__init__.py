"""mcgs_warp.kernels: Warp kernels and functions for Gaussian splatting and SLAM.

A library in its own right: it depends on ``warp`` and ``numpy`` only, so other
Warp projects can import camera models, SE(3) helpers and the differentiable
splatting pipeline without the SLAM system.

Modules:
    camera      camera models (pinhole+radtan, fisheye, equirectangular) as wp.func
    se3         SE(3)/SO(3) Exp, Log, compose, inverse, adjoint as wp.func
    projection  EWA projection of Gaussians and its adjoint (incl. camera pose)
    launch      per-pixel launches over row bands on all CPU cores
    raycast     ray casting of procedural scenes (synthetic sequences)
    tiles       tile binning with radix-sorted (tile, depth) keys
    blend       front-to-back alpha blending and its adjoint
    background  a background at infinity (sky) by world direction (harmonics + cube map), composited through the transmittance, and its adjoint
    splat       Python stages: project, bin_tiles, blend, their backwards, render, render_backward
    ba          MCBA residuals, Jacobians and the sparse Schur reduction (paper eq. 6-10)
    sweep       plane/sphere-sweep stereo for any camera model, ZNCC costs, left-right check
    propagation PatchMatch-style depth propagation at known poses, multi-view consistency
    refine      dense reprojection, image-guided depth upsampling, patch SAD, epipolar point refinement
    losses      mapping losses (exposure, L1 + SSIM, depth, normal) and their gradients
    mapping     Adam, anchored moves (eq. 12-13), scale regularizer
    reference   NumPy float64 brute-force twin used by the tests
"""

from .camera import EQUIRECTANGULAR, FAR, FISHEYE, MODEL_IDS, NEAR, PINHOLE, Camera, make_camera
from .se3 import mat66, vec6
from .splat import (
    Gaussians,
    Gradients,
    Projection,
    Rendered,
    SplatGradients,
    TileBins,
    Views,
    bin_tiles,
    blend,
    blend_backward,
    cpu_workers,
    project,
    project_backward,
    render,
    render_backward,
)

__all__ = [
    "Camera",
    "EQUIRECTANGULAR",
    "FAR",
    "FISHEYE",
    "Gaussians",
    "Gradients",
    "MODEL_IDS",
    "NEAR",
    "PINHOLE",
    "Projection",
    "Rendered",
    "SplatGradients",
    "TileBins",
    "Views",
    "bin_tiles",
    "blend",
    "blend_backward",
    "cpu_workers",
    "make_camera",
    "mat66",
    "project",
    "project_backward",
    "render",
    "render_backward",
    "vec6",
]
