"""Regenerate the bundled Panasonic 18650PF example data from the shared data set.

    examples/panasonic-25degC/        25 degC: hppc.mat, hppc-soc-steps.mat, ocv-c20.mat,
                                      us06.mat, hwfet-a.mat (the one-temperature example)
    examples/panasonic-temperature/   0degC/, n10degC/, n20degC/: hppc.mat,
                                      hppc-soc-steps.mat, us06.mat, hwfet.mat (with the
                                      25 degC files above: the model over temperature)

Trimmed copies: only the fields ecmgen reads (Time, Current, Voltage, Ah,
Battery_Temp_degC) as float64, every row with a cell voltage kept (one row logged at 0 V
after the -20 degC SOC steps is not), in the same `meas` struct so the same reader applies. The output is byte-reproducible (fixed .mat header text, no timestamp).

    python examples/make_panasonic_example.py [--source DIR] [--out DIR]
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np
import scipy.io

HERE = Path(__file__).resolve().parent
DEFAULT_SOURCE = HERE.parent.parent / "shared" / "data"
# (source folder under the shared data, example folder under examples/, files)
SETS = (
    ("panasonic-18650pf-25degC", "panasonic-25degC",
     ("hppc.mat", "hppc-soc-steps.mat", "ocv-c20.mat", "us06.mat", "hwfet-a.mat")),
    ("panasonic-18650pf-0degC", "panasonic-temperature/0degC",
     ("hppc.mat", "hppc-soc-steps.mat", "us06.mat", "hwfet.mat")),
    ("panasonic-18650pf-n10degC", "panasonic-temperature/n10degC",
     ("hppc.mat", "hppc-soc-steps.mat", "us06.mat", "hwfet.mat")),
    ("panasonic-18650pf-n20degC", "panasonic-temperature/n20degC",
     ("hppc.mat", "hppc-soc-steps.mat", "us06.mat", "hwfet.mat")),
)
FIELDS = ("Time", "Current", "Voltage", "Ah", "Battery_Temp_degC")
VALID_V = (0.5, 6.0)       # a row outside this is no cell voltage (ecmgen's reader agrees)
# savemat stamps "Created on: <now>" into the 116-byte text header; pin it so that
# regenerating gives identical bytes (and no spurious diffs in git).
HEADER_TEXT = (b"MATLAB 5.0 MAT-file, trimmed copy of Panasonic 18650PF data "
               b"(Kollmeyer 2018, doi:10.17632/wykht8y7tg.1) for ecmgen")


def trim(source: Path, out: Path) -> int:
    meas = scipy.io.loadmat(source, squeeze_me=True, struct_as_record=False,
                            chars_as_strings=False)["meas"]
    volts = np.asarray(meas.Voltage, dtype=np.float64)
    # rows logged with the cell disconnected (the -20 degC SOC-step record ends with one
    # at 0 V, which ecmgen rightly refuses as a cell voltage): left out
    keep = (volts >= VALID_V[0]) & (volts <= VALID_V[1])
    trimmed = {name: np.asarray(getattr(meas, name), dtype=np.float64)[keep].reshape(-1, 1)
               for name in FIELDS}
    buf = io.BytesIO()
    scipy.io.savemat(buf, {"meas": trimmed}, do_compression=True, oned_as="column")
    data = bytearray(buf.getvalue())
    assert len(HEADER_TEXT) <= 116 and data[:6] == b"MATLAB"
    data[:116] = HEADER_TEXT.ljust(116, b" ")
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_bytes(bytes(data))
    tmp.replace(out)
    return len(data)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=DEFAULT_SOURCE,
                        help="the shared data folder (holds panasonic-18650pf-*)")
    parser.add_argument("--out", type=Path, default=HERE, help="the examples folder")
    args = parser.parse_args(argv)
    total = 0
    for folder, example, names in SETS:
        out = args.out / example
        out.mkdir(parents=True, exist_ok=True)
        for name in names:
            size = trim(args.source / folder / name, out / name)
            total += size
            print(f"{out / name}: {size / 1e6:.2f} MB")
    print(f"total {total / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
