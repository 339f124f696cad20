"""Adam over Warp parameter arrays (one kernel launch per parameter group)."""

from __future__ import annotations

import numpy as np
import warp as wp


def flat(a: wp.array) -> wp.array:
    """Zero-copy flat float32 view of a (vector-typed) Warp array."""
    return a.view(wp.float32).flatten() if a.dtype != wp.float32 else a.flatten()


class Adam:
    """Adam with per-group learning rates; ``params`` maps a name to a Warp array."""

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
        from ..kernels.mapping import adam_kernel

        b1, b2 = self.betas
        for name, p in params.items():
            lr = self.lrs.get(name, 0.0)
            if lr <= 0 or name not in grads:
                continue
            pf, gf = flat(p), flat(grads[name])
            if name not in self.state or self.state[name][0].shape[0] != pf.shape[0]:
                self.state[name] = (wp.zeros_like(pf), wp.zeros_like(pf), 0)
            m, v, t = self.state[name]
            t += 1
            self.state[name] = (m, v, t)
            wp.launch(adam_kernel, dim=pf.shape[0], inputs=[pf, gf, m, v, lr, b1, b2, self.eps, 1 - b1**t, 1 - b2**t], device=p.device)

    def state_arrays(self) -> dict:
        """Moments and step counts as NumPy arrays (for checkpoints)."""
        out = {}
        for name, (m, v, t) in self.state.items():
            out[f"{name}.m"], out[f"{name}.v"], out[f"{name}.t"] = m.numpy().copy(), v.numpy().copy(), np.array(t)
        return out

    def load_state_arrays(self, arrays: dict, device) -> None:
        self.state = {}
        for key in arrays:
            if key.endswith(".m"):
                name = key[:-2]
                self.state[name] = (
                    wp.array(arrays[f"{name}.m"], dtype=float, device=device),
                    wp.array(arrays[f"{name}.v"], dtype=float, device=device),
                    int(arrays[f"{name}.t"]),
                )
