"""Leaving one SOC level out for every candidate smoothing weight at once: the held-out
errors behind the whole-test fit's choice of its smoothing weight
(:func:`ecmgen.fit.curve_levels.choose_penalty`).

Per left-out level the weights share everything but the penalty: the fold's normal
equations, the elimination of the free columns (:func:`ecmgen.fit.lsq.solve_bounded_many`)
and the projection that refits the free nuisance columns on the left-out rows (one SVD of
those columns, with ``numpy.linalg.lstsq``'s rank cut-off, for all weights)."""

from __future__ import annotations

import numpy as np

from .lsq import solve_bounded_many


def held_out_errors(prob, z: np.ndarray, lay: dict, penalties, levels: list,
                    normal: tuple | None = None) -> np.ndarray:
    """For each weight of ``penalties``, the sum over ``levels`` (row indices of each level)
    of the left-out rows' squared residual after refitting only the free columns there,
    each fold fitted on the other rows at that weight. ``normal``: (z'z, z'y), if known."""
    gram, g = normal if normal is not None else (z.T @ z, z.T @ prob.yw)
    free = lay["free"]
    errors = np.zeros(len(penalties))
    for r in levels:
        zk, yk = z[r], prob.yw[r]
        gk, qk = gram - zk.T @ zk, g - zk.T @ yk
        xs = solve_bounded_many([mq[:2] for mq in prob.regularised_many(gk, qk, lay, penalties)],
                                free)
        res = yk[:, None] - zk @ xs.T
        basis = _range_basis(zk[:, free])
        if basis is not None:
            res = res - basis @ (basis.T @ res)
        errors += np.einsum("ij,ij->j", res, res)
    return errors


def _range_basis(f: np.ndarray) -> np.ndarray | None:
    """An orthonormal basis of the column space of ``f`` (None when it is empty), with the
    rank ``numpy.linalg.lstsq`` gives it (singular values above eps * max(shape) of the
    largest)."""
    f = f[:, np.any(f != 0.0, axis=0)]
    if not f.size:
        return None
    u, s, _ = np.linalg.svd(f, full_matrices=False)
    keep = s > np.finfo(float).eps * max(f.shape) * s[0]
    return u[:, keep]
