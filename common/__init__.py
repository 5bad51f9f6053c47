"""Helpers shared by the pipeline and the tracker: atomic output commits, a command's checked outputs,
the command-line conventions, the one CSV table reader, the Dask client, lazy package exports, the interactive map builder."""

from common.exports import lazy_exports

_EXPORTS = {
    "atomic_paths": "atomic",
    "pid_alive": "atomic",
    "EXIT_ERROR": "cli",
    "EXIT_OK": "cli",
    "EXIT_USAGE": "cli",
    "attach_negative_values": "cli",
    "count": "cli",
    "number": "cli",
    "quiet_parent": "cli",
    "run_cli": "cli",
    "Output": "outputs",
    "OutputError": "outputs",
    "command_outputs": "outputs",
    "input_files": "outputs",
    "remove_stale_stages": "outputs",
    "remove_stale_temps": "atomic",
    "scratch_dir": "atomic",
    "get_client": "dask",
    "using_client": "dask",
    "lazy_exports": "exports",
    "numeric_column": "tables",
    "read_csv_table": "tables",
    "LeafletMap": "maps",
    "covariance_popup": "maps",
    "density_map": "maps",
    "VectorSource": "maps",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
