"""Test kernels evaluating the camera wp.funcs on arrays of points."""

import warp as wp

from mcgs_warp.kernels.camera import (
    Camera,
    camera_in_domain,
    camera_jacobian,
    camera_jacobian_vjp,
    camera_project,
    camera_unproject,
    camera_depth,
    mat23,
)


@wp.kernel
def eval_camera_kernel(
    cam: Camera,
    p: wp.array(dtype=wp.vec3),
    G: wp.array(dtype=mat23),
    uv: wp.array(dtype=wp.vec2),
    J: wp.array(dtype=mat23),
    vjp: wp.array(dtype=wp.vec3),
    back: wp.array(dtype=wp.vec3),
    ok: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    x = p[i]
    uv[i] = camera_project(cam, x)
    J[i] = camera_jacobian(cam, x)
    vjp[i] = camera_jacobian_vjp(cam, x, G[i])
    back[i] = camera_unproject(cam, uv[i], camera_depth(cam, x))
    ok[i] = wp.where(camera_in_domain(cam, x, 0.01, 100.0), 1, 0)


def eval_camera(cam, p, G, device="cpu"):
    """Returns dict of numpy arrays: uv, J, vjp, back (unprojected), ok."""
    n = len(p)
    arrs = dict(
        uv=wp.zeros(n, dtype=wp.vec2, device=device),
        J=wp.zeros(n, dtype=mat23, device=device),
        vjp=wp.zeros(n, dtype=wp.vec3, device=device),
        back=wp.zeros(n, dtype=wp.vec3, device=device),
        ok=wp.zeros(n, dtype=wp.int32, device=device),
    )
    wp.launch(
        eval_camera_kernel,
        dim=n,
        inputs=[cam, wp.array(p.astype("float32"), dtype=wp.vec3, device=device), wp.array(G.astype("float32"), dtype=mat23, device=device)],
        outputs=list(arrs.values()),
        device=device,
    )
    return {k: v.numpy() for k, v in arrs.items()}
