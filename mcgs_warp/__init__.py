"""mcgs_warp: multi-camera Gaussian-Splatting SLAM on NVIDIA Warp.

Kept light on purpose: ``import mcgs_warp.kernels`` must not pull in OpenCV,
SciPy or USD (DESIGN.md, "Layers").
"""

__version__ = "0.1.0"
