"""The generated C's tables read back from the C text and compared with the model at its
grid points, without ecmgen.c.codegen's table functions or the CSpec (which the C
references and the golden vectors share: a quantisation or layout error there would be
bit-exact to itself). The layout is the runtime's documented one (c_runtime/README.md,
"Tables"): per direction, temperature row after row, SOC point after point, the
parameters r0, r_fast, tau_fast, r_slow, tau_slow (r0, r_fast, r_slow with the time
constants per row in ``tk``); the branches per row r_diff, tau_diff, i0; the OCV row after
row. Float: each value a pair (value, float32 difference to the next row), the value the
model's as float32. Fixed point: round(value 2^Q) half up, so within half an LSB of the
formats the header states."""

from __future__ import annotations

import re

import numpy as np
import pytest

from ecmgen.c.codegen import generate_c
from test_codegen_helpers import fitter_layout_model, temperature_model

ARRAY = re.compile(r"static const (?:float|int32_t) (\w+)\[(\d+)\] = \{(.*?)\};", re.S)


def _arrays(src: str) -> dict[str, np.ndarray]:
    out = {}
    for m in ARRAY.finditer(src):
        toks = [t for t in re.split(r"[,\s]+", m.group(3)) if t]
        out[m.group(1)] = np.array([float(t.rstrip("f")) for t in toks])
    return out


def _struct(src: str) -> list[dict[str, str]]:
    """Per direction (discharge, charge) the array names of .rows, .tk, .branch."""
    dirs = re.findall(r"\{ \.g = .*?, \.rows = (\w+)(?:, \.tk = (\w+))?(?:, \.branch = (\w+))? \}",
                      src)
    return [{"rows": r, "tk": t or None, "branch": b or None} for r, t, b in dirs]


def _formats(header: str, macro: str) -> dict[str, int]:
    return {k: int(v) for k, v in re.findall(rf"#define {macro}_(\w+) (\d+)\b", header)}


def check_tables(model, folder, prefix: str, numeric: str) -> None:
    """AssertionError unless every table value of the C in ``folder`` is the model's at its
    grid point (float32, or within half an LSB)."""
    s = "q" if numeric == "fixed" else "f32"
    src = (folder / f"{prefix}_ecm_{s}.c").read_text()
    arrays = _arrays(src)
    fixed = numeric == "fixed"
    q = _formats((folder / f"{prefix}_ecm_{s}.h").read_text(), f"{prefix.upper()}_ECM_Q") \
        if fixed else {}

    def compare(got, want, qf, what):
        got = np.asarray(got, dtype=np.float64).reshape(-1)
        want = np.asarray(want, dtype=np.float64).reshape(-1)
        if fixed:
            err = np.abs(got / 2.0 ** qf - want) * 2.0 ** qf       # in LSB
            bad = np.flatnonzero(err > 0.5 + 1e-9)
            assert bad.size == 0, f"{what}: {bad.size} values off by more than half an " \
                                  f"LSB (worst {err.max():.3f} LSB at {bad[0]})"
        else:   # the model's value as float32; a row the generator interpolated (another
            # table's temperature) may round to its neighbour: one float32 spacing
            got, w32 = got.astype(np.float32), want.astype(np.float32)
            bad = np.flatnonzero(np.abs(got - w32) > np.spacing(np.abs(w32)))
            assert bad.size == 0, f"{what}: {bad.size} values not the model's float32 " \
                                  f"(first at {bad[0]}: {got[bad[0]]!r} for {want[bad[0]]!r})"

    def values(name):
        a = arrays[name]
        return a if fixed else a.reshape(-1, 2)[:, 0].reshape(-1)    # (value, difference)

    # the C's temperature rows: the union of every table's breakpoints, each table linear
    # in temperature between its own rows (clamped) at the others
    temps_of = [np.atleast_1d(np.asarray(getattr(t, "temperature_c", [25.0]), float))
                for t in (model.discharge, model.charge, model.ocv)]
    union = np.unique(np.concatenate(temps_of))
    grid = None
    if "temp_c" in arrays:
        grid = union
        compare(arrays["temp_c"], union, 8, "temp_c")          # degC, Q8 in fixed point

    def at_grid(values, temps):
        values = np.asarray(values, dtype=np.float64)
        if grid is None or values.shape[0] == 1:
            return np.repeat(values[:1], 1 if grid is None else grid.size, axis=0)
        cols = values.reshape(values.shape[0], -1)
        out = np.stack([np.interp(grid, temps, cols[:, k]) for k in range(cols.shape[1])], 1)
        return out.reshape((grid.size,) + values.shape[1:])

    dirs = _struct(src)
    for table, d in zip((model.discharge, model.charge), dirs):
        temps = np.atleast_1d(np.asarray(table.temperature_c, dtype=np.float64))
        table_at = {f: None if getattr(table, f, None) is None else at_grid(getattr(table, f), temps)
                    for f in ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm",
                              "tau_slow_s", "r_diff_ohm", "tau_diff_s", "i0_a")}
        n_t, n_s = table_at["r0_ohm"].shape
        tau_t = d["tk"] is not None
        cols = [("r0_ohm", "R0"), ("r_fast_ohm", "RF"), ("tau_fast_s", "T"),
                ("r_slow_ohm", "RS"), ("tau_slow_s", "T")]
        rows_cols = [c for c in cols if not (tau_t and c[0].startswith("tau"))]
        rows = values(d["rows"]).reshape(n_t, n_s, len(rows_cols))
        for k, (field, qf) in enumerate(rows_cols):
            compare(rows[:, :, k], table_at[field], q.get(qf), f"{d['rows']} {field}")
        if tau_t:
            tk = values(d["tk"]).reshape(n_t, 2)
            for k, field in enumerate(("tau_fast_s", "tau_slow_s")):
                compare(tk[:, k], table_at[field][:, 0], q.get("T"), f"{d['tk']} {field}")
        if d["branch"] is not None:
            names = [(f, qf) for f, qf in (("r_diff_ohm", "RD"), ("tau_diff_s", "T"),
                                          ("i0_a", "I0")) if getattr(table, f) is not None]
            br = values(d["branch"]).reshape(n_t, len(names))
            for k, (field, qf) in enumerate(names):
                compare(br[:, k], table_at[field], q.get(qf), f"{d['branch']} {field}")
    ocv_t = np.atleast_1d(np.asarray(getattr(model.ocv, "temperature_c", [25.0]), float))
    want = at_grid(model.ocv.ocv_v, ocv_t)
    compare(values("ocv_v").reshape(want.shape), want, q.get("V"), "ocv_v")


MODELS = {"over temperature, tau per point": lambda: temperature_model(branches=True),
          "the fitter's layout (tau per row)": lambda: fitter_layout_model(branches=True)}


@pytest.mark.parametrize("numeric", ["float", "fixed"])
@pytest.mark.parametrize("which", list(MODELS))
def test_the_c_tables_are_the_model_at_its_grid_points(tmp_path, which, numeric):
    model = MODELS[which]()
    generate_c(model, tmp_path, prefix="ind", numeric=numeric)
    check_tables(model, tmp_path, "ind", numeric)


def test_a_wrong_quantisation_is_caught(tmp_path, monkeypatch):
    """The quantiser truncating instead of rounding half up: the golden vectors and the
    references would agree with such C bit for bit; this check does not."""
    import ecmgen.c.qspec as qspec

    def floor_quantize(values, q):
        v = np.floor(np.ldexp(np.asarray(values, dtype=np.float64), q))
        return np.clip(v, -2**31, 2**31 - 1).astype(np.int64)

    model = temperature_model(branches=True)
    monkeypatch.setattr(qspec, "quantize", floor_quantize)
    generate_c(model, tmp_path, prefix="ind", numeric="fixed")
    with pytest.raises(AssertionError, match="more than half an LSB"):
        check_tables(model, tmp_path, "ind", "fixed")
