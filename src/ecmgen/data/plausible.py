"""Is a measurement plausible for one cell? Voltage, current and temperature ranges, with
a hint at the usual cause (a unit declared wrongly) when a value is outside."""

from __future__ import annotations

import numpy as np

from ..errors import InputError

# outside these limits the file is almost surely mislabelled
VOLTAGE_RANGE_V = (0.5, 6.0)
MAX_C_RATE = 50.0            # used when the capacity is known
MAX_CURRENT_A = 2000.0       # used when it is not
# a cell's temperature in a test: below -60 degC no cell works, above 150 degC it is on
# fire; outside that the column is in K or degF, or it is not a temperature
TEMPERATURE_RANGE_C = (-60.0, 150.0)


# a logger switched off writes a row or two of 0 V at a record's end (the Panasonic -20 degC
# steps file): so many rows at either end, at most, are dropped rather than the file refused
MAX_END_ROWS_SHARE = 0.01


def implausible_ends(volts: np.ndarray) -> tuple[int, int]:
    """[first, stop): the record without the runs of implausible voltages at its start
    and end, where they are at most MAX_END_ROWS_SHARE of its rows; (0, n) otherwise
    (a voltage in the wrong unit is wrong everywhere, and is refused by check_voltage)."""
    n = volts.size
    lo, hi = VOLTAGE_RANGE_V
    good = np.flatnonzero((volts >= lo) & (volts <= hi))
    if good.size < 2:
        return 0, n
    first, stop = int(good[0]), int(good[-1]) + 1
    if first + n - stop > MAX_END_ROWS_SHARE * n:
        return 0, n
    return first, stop


def check_temperature(path, temps, loc) -> None:
    lo, hi = TEMPERATURE_RANGE_C
    out = (temps < lo) | (temps > hi)
    if not out.any():
        return
    i = int(np.argmax(out))
    typical = float(np.median(temps))
    hint = (" (kelvin? give degC)" if 200.0 <= typical <= 450.0 else
            " (degF? give degC)" if 100.0 < typical < 200.0 else " (implausible for a cell)")
    raise InputError(path, f"{loc('temperature', i)}: temperature {temps[i]:.6g} degC is "
                           f"outside {lo:g}..{hi:g} degC{hint}")


def check_voltage(path, volts, colmap, loc) -> None:
    lo, hi = VOLTAGE_RANGE_V
    out = (volts < lo) | (volts > hi)
    if not out.any():
        return
    i = int(np.argmax(out))
    typical = float(np.median(np.abs(volts)))
    if colmap.voltage_unit == "V" and lo <= typical / 1000.0 <= hi:
        hint = ": mV declared as V? (voltage_unit = \"mV\")"
    elif colmap.voltage_unit == "mV" and lo <= typical * 1000.0 <= hi:
        hint = ": V declared as mV? (voltage_unit = \"V\")"
    else:
        hint = " (implausible for one cell)"
    raise InputError(path, f"{loc('voltage', i)}: voltage {volts[i]:.6g} V is outside "
                           f"{lo:g}..{hi:g} V{hint}")


def check_current(path, amps, colmap, capacity_ah, loc) -> None:
    i = int(np.argmax(np.abs(amps)))
    peak = abs(float(amps[i]))
    limit = MAX_C_RATE * capacity_ah if capacity_ah is not None else MAX_CURRENT_A
    if peak <= limit:
        return
    if capacity_ah is not None:
        what = (f"current reaches {peak:.6g} A = {peak / capacity_ah:.4g} C for a "
                f"{capacity_ah:g} Ah cell (limit {MAX_C_RATE:g} C)")
    else:
        what = f"current reaches {peak:.6g} A (limit {MAX_CURRENT_A:g} A for one cell)"
    if colmap.current_unit == "A" and peak / 1000.0 <= limit:
        hint = ": mA declared as A? (current_unit = \"mA\")"
    else:
        hint = ": check the current column and its unit"
    raise InputError(path, f"{loc('current', i)}: {what}{hint}")
