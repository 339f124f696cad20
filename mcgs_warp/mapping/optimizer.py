"""The one Adam of the mapping stage: Gaussians, per-image exposures and keyframe pose
corrections are all stepped by :func:`mcgs_warp.kernels.mapping.adam_kernel` on the
device (one launch per parameter group).

A group is a named flat float32 array with its own moments and step count (bias
correction). The Gaussian groups are named after their parameter; exposures and pose
corrections get a group per keyframe (``exposure{k}``, ``pose{k}``), so a keyframe's
bias correction counts its own steps, whichever keyframes were visited in between.
"""

from __future__ import annotations

import numpy as np
import warp as wp


def flat(a: wp.array) -> wp.array:
    """Zero-copy flat float32 view of a (vector-typed) Warp array."""
    return a.view(wp.float32).flatten() if a.dtype != wp.float32 else a.flatten()


class Adam:
    """Adam with per-group learning rates ``lrs`` (name -> lr; groups stepped with
    :meth:`step_group` pass theirs); ``state``: name -> (m, v, step count)."""

    def __init__(self, lrs: dict, betas=(0.9, 0.999), eps: float = 1e-15):
        self.lrs = dict(lrs)
        self.betas = betas
        self.eps = eps
        self.state: dict = {}  # name -> (m, v, step)

    def remap(self, name: str, index: np.ndarray, n_new: int, width: int) -> None:
        """Carry the moments of kept/copied entries (``index`` [n_new], -1 = new entry)."""
        if name not in self.state:
            return
        m, v, t = self.state[name]
        dev = m.device
        mo = m.numpy().reshape(-1, width)
        vo = v.numpy().reshape(-1, width)
        mn = np.zeros((n_new, width), np.float32)
        vn = np.zeros((n_new, width), np.float32)
        ok = index >= 0
        mn[ok] = mo[index[ok]]
        vn[ok] = vo[index[ok]]
        self.state[name] = (wp.array(mn.ravel(), dtype=float, device=dev), wp.array(vn.ravel(), dtype=float, device=dev), t)

    def step(self, params: dict, grads: dict) -> None:
        """Step every group of ``params`` (name -> Warp array) that has a positive
        learning rate in ``lrs`` and a gradient in ``grads`` (same shapes)."""
        for name, p in params.items():
            lr = self.lrs.get(name, 0.0)
            if lr > 0 and name in grads:
                self.step_group(name, p, grads[name], lr)

    def step_group(self, name: str, param: wp.array, grad: wp.array, lr: float) -> None:
        """One in-place Adam step of group ``name``: ``param`` and ``grad`` are Warp arrays
        of the same size (any vector dtype of float32; contiguous), ``lr`` in the
        parameter's units per step. Moments are (re)made when the size changes."""
        from ..kernels.mapping import adam_kernel

        b1, b2 = self.betas
        pf, gf = flat(param), flat(grad)
        if name not in self.state or self.state[name][0].shape[0] != pf.shape[0]:
            self.state[name] = (wp.zeros_like(pf), wp.zeros_like(pf), 0)
        m, v, t = self.state[name]
        t += 1
        self.state[name] = (m, v, t)
        wp.launch(adam_kernel, dim=pf.shape[0], inputs=[pf, gf, m, v, lr, b1, b2, self.eps, 1 - b1**t, 1 - b2**t], device=pf.device)

    def state_arrays(self) -> dict:
        """Moments and step counts as NumPy arrays (for checkpoints)."""
        out = {}
        for name, (m, v, t) in self.state.items():
            out[f"{name}.m"], out[f"{name}.v"], out[f"{name}.t"] = m.numpy().copy(), v.numpy().copy(), np.array(t)
        return out

    def load_state_arrays(self, arrays: dict, device) -> None:
        """Restore what :meth:`state_arrays` gave (moments on ``device``)."""
        self.state = {}
        for key in arrays:
            if key.endswith(".m"):
                name = key[:-2]
                self.state[name] = (
                    wp.array(arrays[f"{name}.m"], dtype=float, device=device),
                    wp.array(arrays[f"{name}.v"], dtype=float, device=device),
                    int(arrays[f"{name}.t"]),
                )
