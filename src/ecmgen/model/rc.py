"""The first-order recursion u_k = a_k u_{k-1} + b_k behind every RC state.

One definition, used by the simulation (the RC pairs), the effects (hysteresis state,
extra RC pair) and diagnose (signatures): :mod:`ecmgen.model.simulate` and
:mod:`ecmgen.model.effects` both import it from here, so neither imports the other
for it.
"""

from __future__ import annotations

import numpy as np


def rc_recurrence(a: np.ndarray, b: np.ndarray, u0: float = 0.0) -> np.ndarray:
    """u_k = a_k * u_{k-1} + b_k, u_{-1} = u0. Time-varying first-order recursion."""
    out = np.empty_like(b)
    u = float(u0)
    # Plain Python floats: ~10x faster than indexing numpy scalars; n is at most ~1e6.
    for k, (ak, bk) in enumerate(zip(a.tolist(), b.tolist())):
        u = ak * u + bk
        out[k] = u
    return out
