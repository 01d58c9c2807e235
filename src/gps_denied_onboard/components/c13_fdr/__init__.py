"""C13 flight data recorder: the ``FdrClient`` contract, the JSON-lines recorder and its reader.

``provenance.run_inputs`` (the start record's hashes) is not re-exported: it imports the model package,
which the reader's users (``gdnav fdr summary``) do not need."""

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
    FdrHealth,
    FlightDataRecorder,
    NotRegularFileError,
    list_images,
    list_segments,
    parse_line,
    read_records,
    read_records_newest_first,
    refused_files,
    to_jsonable,
)

__all__ = [
    "EstimateRecord",
    "FdrClient",
    "FdrHealth",
    "FdrReadError",
    "FdrReader",
    "FdrRun",
    "FixRecord",
    "FlightDataRecorder",
    "FrameError",
    "FrameRefusal",
    "NotRegularFileError",
    "ProvenanceChange",
    "RunStop",
    "list_images",
    "list_segments",
    "parse_line",
    "read_records",
    "read_records_newest_first",
    "refused_files",
    "to_jsonable",
]
