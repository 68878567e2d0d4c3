"""Stage 1, measurement files in: each record becomes a :class:`TimeSeries`
(:mod:`.measure`), a pulse test its pulses and DC-IR table ``R(t) = dV/dI``
(:mod:`.dcir`), and the OCV(SOC) table comes from a table, a low-rate test or the rests
of a pulse test (:mod:`.ocv`). Imports only :mod:`ecmgen.errors` and :mod:`ecmgen.files`.
"""

from .dcir import DcirTable, Pulse, extract_dcir, find_pulses, read_dcir_csv
from .measure import ColumnMap, TimeSeries, read_timeseries, write_timeseries_csv
from .ocv import OcvTable, ocv_from_low_rate, ocv_from_pulse_rests, read_ocv_table

__all__ = ["ColumnMap", "DcirTable", "OcvTable", "Pulse", "TimeSeries", "extract_dcir",
           "find_pulses", "ocv_from_low_rate", "ocv_from_pulse_rests", "read_dcir_csv",
           "read_ocv_table", "read_timeseries", "write_timeseries_csv"]
