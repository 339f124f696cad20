"""3DGS PLY (the reference layout that splat viewers read), binary little endian:
``x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3``, with opacity as a logit,
scales as logs, rotations real part first ``(w, x, y, z)`` and colour as the SH DC
term ``(rgb - 0.5) / 0.28209479``; then our ``measured`` (1: the Gaussian was placed at a
measured depth, 0: at a guessed one), which splat viewers ignore as an unknown property.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_write

SH_C0 = 0.28209479177387814
FIELDS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def write_ply(path, params: dict) -> None:
    """Write map parameters (``means``, ``quats`` xyzw, ``log_scales``, ``opacity_logits``,
    ``colors``; with ``measured`` [N] bool, that property too)."""
    n = len(params["means"])
    q = np.asarray(params["quats"], np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    # normalize, but leave quaternions that are unit to float32 precision as they are, so that
    # reading a file and writing it again gives the same bytes
    q = np.where(np.abs(norm - 1.0) < 1e-6, q, q / norm)
    fields = FIELDS + (["measured"] if params.get("measured") is not None else [])
    data = np.zeros((n, len(fields)), np.float32)
    data[:, 0:3] = params["means"]
    data[:, 6:9] = (np.asarray(params["colors"]) - 0.5) / SH_C0
    data[:, 9] = params["opacity_logits"]
    data[:, 10:13] = params["log_scales"]
    data[:, 13] = q[:, 3]
    data[:, 14:17] = q[:, :3]
    if len(fields) > len(FIELDS):
        data[:, len(FIELDS)] = np.asarray(params["measured"], bool)
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n" + "".join(f"property float {f}\n" for f in fields) + "end_header\n"
    with atomic_write(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.astype("<f4").tobytes())


def read_ply(path) -> dict:
    """Read a 3DGS PLY written by :func:`write_ply` (or any with at least those float fields;
    ``measured`` is None where the file has no such property)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "PLY file not found")
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise InputError(path, None, "not a PLY file (missing 'ply' / 'end_header')")
    header = raw[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise InputError(path, "format", "expected binary_little_endian 1.0")
    n = next((int(h.split()[2]) for h in header if h.startswith("element vertex")), None)
    props = [h.split()[2] for h in header if h.startswith("property float")]
    if n is None or any(f not in props for f in FIELDS):
        raise InputError(path, "header", f"expected a vertex element with float properties {', '.join(FIELDS)}")
    body = np.frombuffer(raw[end + len(b"end_header\n") :], dtype="<f4")
    if body.size != n * len(props):
        raise InputError(path, None, f"expected {n} vertices of {len(props)} floats, file is truncated or malformed")
    data = body.reshape(n, len(props))
    col = {name: data[:, i] for i, name in enumerate(props)}
    return {
        "means": np.stack([col["x"], col["y"], col["z"]], 1),
        "quats": np.stack([col["rot_1"], col["rot_2"], col["rot_3"], col["rot_0"]], 1),
        "log_scales": np.stack([col["scale_0"], col["scale_1"], col["scale_2"]], 1),
        "opacity_logits": col["opacity"].copy(),
        "colors": np.stack([col["f_dc_0"], col["f_dc_1"], col["f_dc_2"]], 1) * SH_C0 + 0.5,
        "measured": col["measured"] > 0.5 if "measured" in col else None,
    }
