"""Regenerate examples/panasonic-25degC/*.mat from the shared Panasonic 18650PF data.

Trimmed copies: only the fields ecmgen reads (Time, Current, Voltage, Ah,
Battery_Temp_degC) as float64, every row kept, in the same `meas` struct so the same
reader applies. The output is byte-reproducible (fixed .mat header text, no timestamp).

    python examples/make_panasonic_example.py [--source DIR] [--out DIR]
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np
import scipy.io

HERE = Path(__file__).resolve().parent
DEFAULT_SOURCE = HERE.parent.parent / "shared" / "data" / "panasonic-18650pf-25degC"
DEFAULT_OUT = HERE / "panasonic-25degC"
FILES = ("hppc.mat", "ocv-c20.mat", "us06.mat", "hwfet-a.mat")
FIELDS = ("Time", "Current", "Voltage", "Ah", "Battery_Temp_degC")
# savemat stamps "Created on: <now>" into the 116-byte text header; pin it so that
# regenerating gives identical bytes (and no spurious diffs in git).
HEADER_TEXT = (b"MATLAB 5.0 MAT-file, trimmed copy of Panasonic 18650PF data "
               b"(Kollmeyer 2018, doi:10.17632/wykht8y7tg.1) for ecmgen")


def trim(source: Path, out: Path) -> int:
    meas = scipy.io.loadmat(source, squeeze_me=True, struct_as_record=False,
                            chars_as_strings=False)["meas"]
    trimmed = {name: np.asarray(getattr(meas, name), dtype=np.float64).reshape(-1, 1)
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
    parser.add_argument("--source", type=Path, default=DEFAULT_SOURCE)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    total = 0
    for name in FILES:
        size = trim(args.source / name, args.out / name)
        total += size
        print(f"{args.out / name}: {size / 1e6:.2f} MB")
    print(f"total {total / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
