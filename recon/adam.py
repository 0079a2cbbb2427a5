"""Adam (Kingma & Ba 2015) on a dict of flat Dr.Jit Float parameters, with its state in plain
arrays so that checkpoints never depend on Dr.Jit's private optimiser state.

Shared by the solver (:mod:`recon.solver`, voxels and network) and the network's warm start
(:mod:`recon.field`).
"""
from __future__ import annotations

import math

import numpy as np

from sonarsim.errors import FormatError

from ._jit import jit


class Adam:
    """Adam (Kingma & Ba) on a dict of flat Dr.Jit Float parameters, state in plain arrays.

    ``params[name]`` are grad-enabled leaves; :meth:`step` reads their gradients, updates
    the moments ``m``, ``v`` and the step count ``t`` (bias-corrected), writes new leaves
    and clears the gradients. :meth:`state` / :meth:`load` give NumPy copies for checkpoints.
    """

    def __init__(self, params: dict, lr: float, beta1=0.9, beta2=0.999, epsilon=1e-8):
        import drjit as dr
        m = jit()
        self.m_, self.lr, self.b1, self.b2, self.eps, self.t = m, lr, beta1, beta2, epsilon, 0
        self.params = {}
        for k, v in params.items():
            x = m.Float(np.asarray(v, dtype=np.float32))
            dr.enable_grad(x)
            self.params[k] = x
        self.m = {k: dr.zeros(m.Float, dr.width(v)) for k, v in self.params.items()}
        self.v = {k: dr.zeros(m.Float, dr.width(v)) for k, v in self.params.items()}

    def step(self):
        import drjit as dr
        self.t += 1
        c1 = 1.0 - self.b1 ** self.t
        c2 = 1.0 - self.b2 ** self.t
        # Per-step scalars as opaque values: literals would compile new kernels every step.
        step = dr.opaque(self.m_.Float, self.lr * math.sqrt(c2) / c1)
        eps = dr.opaque(self.m_.Float, self.eps * math.sqrt(c2))
        new = {}
        for k, x in self.params.items():
            g = dr.grad(x)
            mk = self.b1 * self.m[k] + (1.0 - self.b1) * g
            vk = self.b2 * self.v[k] + (1.0 - self.b2) * dr.square(g)
            xk = dr.detach(x) - step * mk / (dr.sqrt(vk) + eps)
            dr.eval(mk, vk, xk)
            self.m[k], self.v[k] = mk, vk
            dr.enable_grad(xk)
            new[k] = xk
        self.params = new

    def state(self) -> dict:
        import drjit as dr
        out = {"t": np.array(self.t, dtype=np.int64)}
        for k in self.params:
            out[f"param/{k}"] = np.asarray(dr.detach(self.params[k]))
            out[f"adam_m/{k}"] = np.asarray(self.m[k])
            out[f"adam_v/{k}"] = np.asarray(self.v[k])
        return out

    def load(self, state: dict):
        import drjit as dr
        m = self.m_
        self.t = int(state["t"])
        for k in list(self.params):
            for name in (f"param/{k}", f"adam_m/{k}", f"adam_v/{k}"):
                if name not in state or state[name].shape != (dr.width(self.params[k]),):
                    raise FormatError(f"checkpoint: entry {name} missing or of the wrong size")
            x = m.Float(state[f"param/{k}"])
            dr.enable_grad(x)
            self.params[k] = x
            self.m[k] = m.Float(state[f"adam_m/{k}"])
            self.v[k] = m.Float(state[f"adam_v/{k}"])


# ---------------------------------------------------------------------------------------
# Loss
