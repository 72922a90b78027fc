"""A Python client for the Patchwork terrain database.

    from patchwork_client import Client
    with Client("127.0.0.1:50051") as c:
        heights = c.tile((-119.0, 34.45, -118.9, 34.55), 512, 512, error=5.0)

Every RPC of the daemon's Terrain and Admin services has a method on :class:`Client`; arrays
come back as numpy, with NaN where there is no data. :func:`resample` blends streamed patches
into a tile on the client, as the daemon's ResampleTile does.
"""

from .client import (
    AccuracySource,
    Camera,
    ChangeEvent,
    ChangeRegion,
    Client,
    Conflict,
    IngestPhase,
    IngestResult,
    Mesh,
    Outcome,
    Survey,
    SurveyStatus,
    TileInfo,
    ViewSession,
    ViewStep,
)
from .patches import Patch, resample

__all__ = [
    "AccuracySource",
    "Camera",
    "ChangeEvent",
    "ChangeRegion",
    "Client",
    "Conflict",
    "IngestPhase",
    "IngestResult",
    "Mesh",
    "Outcome",
    "Patch",
    "Survey",
    "SurveyStatus",
    "TileInfo",
    "ViewSession",
    "ViewStep",
    "resample",
]
