"""The shared Panasonic 18650PF data at four temperatures as ecmgen build configs (used by
bench_build_temperature.py and loto_temperature.py).

The data sit beside the checkout in ../shared/data (see its README): per temperature a
pulse test (hppc.mat), its SOC-step record (hppc-soc-steps.mat) and two drive cycles.
"""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
FOLDERS = {"25degC": "panasonic-18650pf-25degC", "0degC": "panasonic-18650pf-0degC",
           "n10degC": "panasonic-18650pf-n10degC", "n20degC": "panasonic-18650pf-n20degC"}
CYCLES = {"25degC": ("us06.mat", "hwfet-a.mat"), "0degC": ("us06.mat", "hwfet.mat"),
          "n10degC": ("us06.mat", "hwfet.mat"), "n20degC": ("us06.mat", "hwfet.mat")}


def cycle_paths(temps=tuple(FOLDERS)) -> list[Path]:
    return [DATA / FOLDERS[t] / c for t in temps for c in CYCLES[t]]


def write_config(path: Path, tests=tuple(FOLDERS), cycles=tuple(FOLDERS), *,
                 methods=("ga", "lm", "curve"), c_numeric=("float", "fixed"),
                 extra: str = "") -> Path:
    """A build config over the pulse tests of ``tests`` validated on the cycles of
    ``cycles`` (keys of FOLDERS), soc0 = 1.0 everywhere."""
    if not DATA.is_dir():
        raise SystemExit(f"shared data not found at {DATA}")
    paths = cycle_paths(cycles)
    lines = ["[cell]", "capacity_ah = 2.9", "[data]", "soc0 = 1.0"]
    if paths:
        lines.append(f'cycle = "{paths[0]}"')
        lines.append("extra_cycles = [" + ", ".join(f'"{p}"' for p in paths[1:]) + "]")
    for t in tests:
        folder = DATA / FOLDERS[t]
        lines += ["[[data.pulse_tests]]", f'file = "{folder / "hppc.mat"}"', "soc0 = 1.0",
                  f'steps = "{folder / "hppc-soc-steps.mat"}"']
    lines += ["[fit]", "methods = [" + ", ".join(f'"{m}"' for m in methods) + "]",
              "[c]", "numeric = [" + ", ".join(f'"{n}"' for n in c_numeric) + "]"]
    path.write_text("\n".join(lines) + "\n" + extra)
    return path
