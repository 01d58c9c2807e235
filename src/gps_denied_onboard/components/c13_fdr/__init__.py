"""C13 flight data recorder: the ``FdrClient`` contract, the JSON-lines recorder and its reader."""

from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.components.c13_fdr.reader import (
    EstimateRecord,
    FdrReader,
    FdrReadError,
    FdrRun,
    FixRecord,
    FrameError,
    FrameRefusal,
    ProvenanceChange,
    RunStop,
)
from gps_denied_onboard.components.c13_fdr.recorder import (
    FlightDataRecorder,
    list_segments,
    parse_line,
    read_records,
    read_records_newest_first,
    to_jsonable,
)

__all__ = [
    "EstimateRecord",
    "FdrClient",
    "FdrReadError",
    "FdrReader",
    "FdrRun",
    "FixRecord",
    "FlightDataRecorder",
    "FrameError",
    "FrameRefusal",
    "ProvenanceChange",
    "RunStop",
    "list_segments",
    "parse_line",
    "read_records",
    "read_records_newest_first",
    "to_jsonable",
]
