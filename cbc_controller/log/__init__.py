"""The campaign file: one HDF5 file per CBC campaign, written document by document.

`CampaignWriter` subscribes to the engine's documents (start, point, fault, link, note, stop)
and appends each one to the file; `read_campaign` and `completed_keys` read it back. The layout
is documented in docs/hdf5_layout.md (root attributes, /metadata, /points/NNNNNN, /events,
/runs); any HDF5 reader can open the files.

The package: `encoding` (the format's constants, attributes, history tables), `journal` (the
crash-safe page journal, described there), `writer` and `reader`.
"""

from .encoding import FORMAT_NAME, FORMAT_VERSION, FOURIER_ORDER, CampaignFileError
from .reader import Campaign, completed_keys, read_campaign, read_timeseries
from .writer import CampaignWriter

__all__ = ["CampaignWriter", "CampaignFileError", "Campaign", "read_campaign", "read_timeseries",
           "completed_keys", "FORMAT_NAME", "FORMAT_VERSION", "FOURIER_ORDER"]
