"""`ecmgen fleet`: the build of every cell x check-up of an ageing study or a production
batch, one task each on Dask (a LocalCluster, or a running cluster), resumable by the
hash of each row's inputs; then the fleet table and its trend plots.

    manifest (:mod:`.manifest`) -> one task per row (:mod:`.task`, on :mod:`.run`'s
    cluster) -> the fleet table (:mod:`.table`), each cell's rates (:mod:`.ageing`) and
    the trend plots (:mod:`.plots`)

Needs the optional dependencies ``pip install 'ecmgen[fleet]'``.
"""

from .manifest import Row, read_manifest, row_key
from .run import FleetResult, run_fleet, write_fleet_table
from .task import Options, Outcome, run_row

__all__ = ["FleetResult", "Options", "Outcome", "Row", "read_manifest", "row_key", "run_fleet",
           "run_row", "write_fleet_table"]
