"""The first-order recursion u_k = a_k u_{k-1} + b_k behind every RC state.

One definition, used by the simulation (the RC pairs), the effects (hysteresis state,
extra RC pair) and diagnose (signatures): :mod:`ecmgen.model.simulate` and
:mod:`ecmgen.model.effects` both import it from here, so neither imports the other
for it.
"""

from __future__ import annotations

import numpy as np


# rows per block: the recursion runs on Python floats (about 10x faster than indexing
# numpy scalars), which take 32 bytes each; converted a block at a time they stay a few
# MB, where a whole 6 M-row record would hold two lists of 200 MB
BLOCK = 1 << 16


def rc_recurrence(a: np.ndarray, b: np.ndarray, u0: float = 0.0) -> np.ndarray:
    """u_k = a_k * u_{k-1} + b_k, u_{-1} = u0. Time-varying first-order recursion."""
    out = np.empty_like(b)
    u = float(u0)
    for start in range(0, len(b), BLOCK):
        block = []
        for ak, bk in zip(a[start:start + BLOCK].tolist(), b[start:start + BLOCK].tolist()):
            u = ak * u + bk
            block.append(u)
        out[start:start + len(block)] = block
    return out
