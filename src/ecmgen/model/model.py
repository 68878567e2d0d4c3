"""The fitted model and its one versioned file, ``model.json``.

Everything downstream (simulation, validation, C code, diagnosis) reads an
:class:`EcmModel`; nothing reads the JSON by hand. The file is written with
round-trip float text (``repr``), keys in a fixed order and no timestamps, so the
same fit gives a byte-identical file and therefore byte-identical generated C.

Model (current positive on charge)::

    v = ocv_v(soc) + i * r0_ohm + u_fast + u_slow
    du_j/dt = -u_j / tau_j + i * r_j / tau_j        (j = fast, slow)

with every parameter a table over SOC, one table per current direction. The OCV table
(:class:`OcvTable`) is made by the OCV stage, :mod:`ecmgen.data.ocv`, and re-exported here.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..data.ocv import OcvTable, _f64, check_ocv
from ..errors import InputError
from ..files import write_atomic

SCHEMA = "ecmgen.model"
SCHEMA_VERSION = 1
DIRECTIONS = ("charge", "discharge")
RC_FIELDS = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")


@dataclass(frozen=True)
class RcTable:
    """2RC parameters over SOC for one current direction.

    soc         breakpoints, strictly increasing in [0, 1]
    r0_ohm      series (ohmic) resistance
    r_fast_ohm, tau_fast_s   fast RC pair (charge transfer / double layer)
    r_slow_ohm, tau_slow_s   slow RC pair (diffusion), tau_fast_s < tau_slow_s
    fit_error   the fit's own residual per breakpoint (units depend on the method)
    converged   False where the fitter did not meet its stopping rule
    """

    soc: np.ndarray
    r0_ohm: np.ndarray
    r_fast_ohm: np.ndarray
    tau_fast_s: np.ndarray
    r_slow_ohm: np.ndarray
    tau_slow_s: np.ndarray
    fit_error: np.ndarray
    converged: np.ndarray

    def at(self, soc) -> dict[str, np.ndarray]:
        """Linearly interpolated parameters at ``soc`` (clamped to the table ends)."""
        return {k: np.interp(soc, self.soc, getattr(self, k)) for k in RC_FIELDS}


@dataclass(frozen=True)
class InputRecord:
    """Provenance of one input file."""

    role: str        # "pulses", "dcir", "ocv", "cycle", ...
    name: str        # file name as given
    sha256: str


@dataclass(frozen=True)
class EcmModel:
    """A fitted 2RC equivalent-circuit model: what model.json holds."""

    capacity_ah: float
    ocv: OcvTable
    charge: RcTable
    discharge: RcTable
    method: str                          # "ga", "lm" or "curve"
    seed: int | None = None
    inputs: tuple[InputRecord, ...] = ()
    notes: tuple[str, ...] = ()          # e.g. "charge parameters copied from discharge"
    direction_deadband_a: float = 0.0    # |i| at or below this keeps the last direction
    effects: tuple[Any, ...] = ()        # optional effects added by `diagnose`
    tool_version: str = __version__

    def table(self, direction: str) -> RcTable:
        return self.charge if direction == "charge" else self.discharge

    def with_effects(self, effects) -> "EcmModel":
        return replace(self, effects=tuple(effects))

    # -- serialisation ----------------------------------------------------------------
    def to_json_dict(self) -> dict:
        def table(t: RcTable) -> dict:
            d = {"soc": _floats(t.soc)}
            for k in RC_FIELDS:
                d[k] = _floats(getattr(t, k))
            d["fit_error"] = _floats(t.fit_error)
            d["converged"] = [bool(c) for c in t.converged]
            return d

        return {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "tool_version": self.tool_version,
            "method": self.method,
            "seed": self.seed,
            "capacity_ah": float(self.capacity_ah),
            "direction_deadband_a": float(self.direction_deadband_a),
            "ocv": {"soc": _floats(self.ocv.soc), "ocv_v": _floats(self.ocv.ocv_v)},
            "rc": {"charge": table(self.charge), "discharge": table(self.discharge)},
            "effects": [_effect_to_json(e) for e in self.effects],
            "inputs": [{"role": r.role, "name": r.name, "sha256": r.sha256} for r in self.inputs],
            "notes": list(self.notes),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_json_dict(), indent=1, allow_nan=False) + "\n"

    def sha256(self) -> str:
        """Hash of the canonical JSON text: names this exact model (C banner, reports)."""
        return hashlib.sha256(self.to_json().encode()).hexdigest()

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        write_atomic(path, self.to_json())
        return path


def _floats(a) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64)]


def _effect_to_json(effect) -> dict:
    return effect.to_json_dict()


def load_model(path: str | Path) -> EcmModel:
    """Read and check a model.json; any problem is an InputError naming the file."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    return model_from_json_dict(raw, path)


def model_from_json_dict(raw: Any, path=None) -> EcmModel:
    if not isinstance(raw, dict) or raw.get("schema") != SCHEMA:
        raise InputError(path, f"not an ecmgen model (missing \"schema\": \"{SCHEMA}\")")
    version = raw.get("schema_version")
    if version != SCHEMA_VERSION:
        raise InputError(path, f"schema_version {version!r} is not supported "
                               f"(this ecmgen reads version {SCHEMA_VERSION})")

    def need(d, key, where):
        if not isinstance(d, dict) or key not in d:
            raise InputError(path, f"missing {where}{key}")
        return d[key]

    capacity = float(_f64([need(raw, "capacity_ah", "")], "capacity_ah", path)[0])
    if capacity <= 0:
        raise InputError(path, f"capacity_ah must be positive, got {capacity}")
    ocv_raw = need(raw, "ocv", "")
    ocv_soc = _f64(need(ocv_raw, "soc", "ocv."), "ocv.soc", path)
    ocv_v = _f64(need(ocv_raw, "ocv_v", "ocv."), "ocv.ocv_v", path)
    check_ocv(ocv_soc, ocv_v, path)

    rc = need(raw, "rc", "")
    tables = {}
    for direction in DIRECTIONS:
        t = need(rc, direction, "rc.")
        where = f"rc.{direction}."
        soc = _f64(need(t, "soc", where), where + "soc", path)
        if np.any(np.diff(soc) <= 0) or soc[0] < 0 or soc[-1] > 1:
            raise InputError(path, f"{where}soc must be strictly increasing within [0, 1]")
        cols = {}
        for k in RC_FIELDS:
            cols[k] = _f64(need(t, k, where), where + k, path)
            if cols[k].shape != soc.shape:
                raise InputError(path, f"{where}{k} has {cols[k].size} values, soc has {soc.size}")
            if np.any(cols[k] < 0) or (k.startswith("tau") and np.any(cols[k] <= 0)):
                raise InputError(path, f"{where}{k} must be positive")
        fit_error = _f64(t.get("fit_error", [0.0] * soc.size), where + "fit_error", path)
        converged = np.asarray(t.get("converged", [True] * soc.size), dtype=bool)
        tables[direction] = RcTable(soc=soc, fit_error=fit_error, converged=converged, **cols)

    effects_raw = raw.get("effects", [])
    effects: tuple = ()
    if effects_raw:
        from .effects import effect_from_json_dict  # optional stage, only when present

        effects = tuple(effect_from_json_dict(e, path) for e in effects_raw)
    inputs = tuple(InputRecord(str(r["role"]), str(r["name"]), str(r["sha256"]))
                   for r in raw.get("inputs", []))
    seed = raw.get("seed")
    return EcmModel(
        capacity_ah=capacity,
        ocv=OcvTable(ocv_soc, ocv_v),
        charge=tables["charge"],
        discharge=tables["discharge"],
        method=str(raw.get("method", "")),
        seed=None if seed is None else int(seed),
        inputs=inputs,
        notes=tuple(str(n) for n in raw.get("notes", [])),
        direction_deadband_a=float(raw.get("direction_deadband_a", 0.0)),
        effects=effects,
        tool_version=str(raw.get("tool_version", "")),
    )

