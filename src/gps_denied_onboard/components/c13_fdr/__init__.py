"""C13 flight data recorder: the ``FdrClient`` contract, the JSON-lines recorder and its reader."""

from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.components.c13_fdr.recorder import (
    FlightDataRecorder,
    list_segments,
    read_records,
    read_records_newest_first,
    to_jsonable,
)

__all__ = [
    "FdrClient",
    "FlightDataRecorder",
    "list_segments",
    "read_records",
    "read_records_newest_first",
    "to_jsonable",
]
