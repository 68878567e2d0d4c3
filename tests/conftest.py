"""Shared test fixtures: where the real data lives, and a small synthetic model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
PANASONIC = SHARED_DATA / "panasonic-18650pf-25degC"
CALCE = SHARED_DATA / "calce-a123-lfp"


def need(path: Path) -> Path:
    """Skip (with the reason) when the shared real data is not beside the checkout."""
    if not path.exists():
        pytest.skip(f"real data not found at {path} (expected ../shared/data beside the repo)")
    return path


@pytest.fixture
def synthetic_model():
    """A plausible NCA-like 2RC model with distinct charge/discharge tables."""
    from ecmgen.model import EcmModel, OcvTable, RcTable

    soc = np.linspace(0.0, 1.0, 11)
    ocv = OcvTable(soc, 3.0 + 1.2 * soc - 0.15 * np.sin(2.5 * soc))

    def table(scale):
        n = soc.size
        return RcTable(soc=soc,
                       r0_ohm=scale * (0.020 + 0.010 * (1 - soc) ** 2),
                       r_fast_ohm=scale * np.full(n, 0.008),
                       tau_fast_s=np.full(n, 1.5),
                       r_slow_ohm=scale * (0.010 + 0.005 * (1 - soc)),
                       tau_slow_s=np.full(n, 40.0),
                       fit_error=np.zeros(n), converged=np.ones(n, bool))

    return EcmModel(capacity_ah=2.9, ocv=ocv, charge=table(0.9), discharge=table(1.0),
                    method="synthetic", seed=0, direction_deadband_a=0.029)
