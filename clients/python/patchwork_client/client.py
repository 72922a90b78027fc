"""The gRPC client: a method per RPC of the Terrain and Admin services, numpy arrays out."""

import queue
from collections import OrderedDict
from dataclasses import dataclass, field, fields, make_dataclass, replace
from enum import Enum
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import grpc
import numpy as np

from ._proto import admin_pb2, admin_pb2_grpc, terrain_pb2, terrain_pb2_grpc
from .patches import Patch, Rect

BACKENDS = {
    "auto": terrain_pb2.BACKEND_AUTO,
    "cpu": terrain_pb2.BACKEND_CPU,
    "gpu": terrain_pb2.BACKEND_GPU,
}


class SurveyStatus(str, Enum):
    """Where a survey, or a file that failed, stands. A ``str``: ``SurveyStatus.ACTIVE ==
    "active"``."""

    ACTIVE = "active"
    RETIRED = "retired"
    FAILED = "failed"
    #: An active survey whose records or chunks do not read back as written, out of the
    #: terrain until its file is ingested again or ``repair`` drops it.
    DAMAGED = "damaged"
    #: A file in the inbox the store could not take now (a full disk): read again once space
    #: is freed or the file changes.
    DEFERRED = "deferred"
    #: A file in the inbox that is not an elevation file the daemon reads.
    SKIPPED = "skipped"


class Outcome(str, Enum):
    """What happened to a file or a survey."""

    INSERTED = "inserted"
    REPLACED = "replaced"
    UNCHANGED = "unchanged"
    RETIRED = "retired"
    FAILED = "failed"


class AccuracySource(str, Enum):
    """Where a survey's accuracy claim came from."""

    SIDECAR = "sidecar"
    FLAG = "flag"
    CONFIG = "config"
    ESTIMATED = "estimated"
    #: Stored before the store recorded it.
    UNKNOWN = "unknown"


class IngestPhase(str, Enum):
    """What an ingest under way is doing."""

    READING = "reading"
    MODELLING = "modelling"
    INDEXING = "indexing"
    COMMITTING = "committing"


def _wire_enum(cls, message_enum, prefix: str) -> Dict[int, Enum]:
    """The map from a wire enum's numbers to the client's enum, by the names the proto gives
    them (``SURVEY_STATUS_ACTIVE`` is ``SurveyStatus.ACTIVE``); the unspecified value is left
    out, and reads as None."""
    return {v.number: cls[v.name[len(prefix):]] for v in message_enum.DESCRIPTOR.values
            if not v.name.endswith("_UNSPECIFIED")}


_STATUS = _wire_enum(SurveyStatus, admin_pb2.SurveyStatus, "SURVEY_STATUS_")
_OUTCOME = _wire_enum(Outcome, admin_pb2.Outcome, "OUTCOME_")
_ACCURACY_SOURCE = _wire_enum(AccuracySource, admin_pb2.AccuracySource, "ACCURACY_SOURCE_")
_PHASE = _wire_enum(IngestPhase, admin_pb2.IngestPhase, "INGEST_PHASE_")


@dataclass(frozen=True)
class Camera:
    """A view: eye and look-at point (plane coordinates in the store's CRS, heights in
    metres), horizontal field of view, viewport width and the error allowed on screen."""

    eye: Tuple[float, float, float]
    look: Tuple[float, float, float]
    fov_deg: float = 60.0
    viewport_px: int = 1024
    pixel_error: float = 1.0

    def to_proto(self) -> "terrain_pb2.ViewCut":
        return terrain_pb2.ViewCut(
            eye_x=self.eye[0], eye_y=self.eye[1], eye_z=self.eye[2],
            look_x=self.look[0], look_y=self.look[1], look_z=self.look[2],
            fov_deg=self.fov_deg, viewport_px=self.viewport_px, pixel_error=self.pixel_error,
        )


@dataclass(frozen=True)
class TileInfo:
    """What the daemon says of a tile besides its heights."""

    #: "cpu" or "gpu": what resampled it.
    backend: str
    #: Patches blended, and the largest error among them (metres).
    patches: int
    max_error: float
    #: The tile's CRS (the one asked for, else the store's): its EPSG code, 0 if it has none,
    #: and its key ("EPSG:n", or a WKT 2 definition).
    crs: int
    crs_key: str = ""
    #: What its heights are measured from: "EPSG:n", "ellipsoidal", or "" where the store
    #: names nothing.
    vertical_crs: str = ""


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh of a uniform cut (:meth:`Client.mesh`)."""

    #: n × 3 float64: x and y in the mesh's CRS (``crs_key``), height in metres.
    vertices: np.ndarray
    #: m × 3 uint32 indices into ``vertices``, counter-clockwise seen from above (x east,
    #: y north).
    triangles: np.ndarray
    #: Vertices and triangles from these on are the skirts' (equal to the counts without).
    skirt_vertices: int
    skirt_triangles: int
    #: The largest distance between the surface and the resampled heights at the grid's
    #: measured vertices (metres), and the farthest void under the surface from data.
    max_deviation: float
    max_hole_reach: float
    #: What the cut resampled: patches blended, their largest error, "cpu" or "gpu", EPSG.
    patches: int
    max_error: float
    backend: str
    crs: int
    crs_key: str = ""


MESH_METHODS = {"rtin": terrain_pb2.MESH_METHOD_RTIN, "quadtree": terrain_pb2.MESH_METHOD_QUADTREE}
MESH_BORDERS = {"shared": terrain_pb2.MESH_BORDER_SHARED, "adaptive": terrain_pb2.MESH_BORDER_ADAPTIVE}


@dataclass(frozen=True)
class Conflict:
    survey: str
    max_m: float
    rms_m: float
    #: Where the other survey's content lies against this one's (east, north, up, metres),
    #: and the RMS difference once it is moved back; None where they could not be
    #: coregistered.
    shift_m: Optional[Tuple[float, float, float]] = None
    rms_after_m: Optional[float] = None
    #: Beyond the shift: the other turned (degrees anticlockwise), its scale, and the slope
    #: of its heights less this one's (metres per kilometre east, north); None where they
    #: could not be coregistered.
    turned_deg: Optional[float] = None
    scale: Optional[float] = None
    tilt_m_per_km: Optional[Tuple[float, float]] = None
    #: Whose claim the evidence finds false: "this", "other", "both" or "" (neither).
    distrusted: str = ""
    #: The test that decided it: "prediction", "detail", "transfer", "noise", "line", "consensus" or
    #: "undetermined", with its statistic and a confidence from 0 to 1.
    decided_by: str = ""
    statistic: float = 0.0
    confidence: float = 0.0
    #: Whether the shift is determined; one that is not blames nobody.
    shift_determined: bool = False
    #: Undetermined: whether this survey takes the tie, never displaced by the other.
    takes_tie: bool = False
    #: Where the ground changed between the two.
    changes: Tuple["ChangeRegion", ...] = ()


@dataclass(frozen=True)
class ChangeRegion:
    """A region where the ground changed between two surveys."""
    #: Which saw the ground last and serves there: "this", "other" or "undated" (an epoch
    #: unknown, or the two overlapping: neither takes precedence).
    later: str
    area_m2: float
    #: The volume gained and lost from the earlier survey to the later (from this survey to
    #: the other where undated), cubic metres.
    gained_m3: float
    lost_m3: float
    #: The largest height change, metres.
    most_m: float
    #: Its extent in the finer survey's CRS: least x, least y, greatest x, greatest y.
    bounds: Tuple[float, ...] = ()


@dataclass(frozen=True)
class Survey:
    id: str
    source: str
    status: SurveyStatus
    error: str
    #: The largest ε of the survey's kernels as served: its own claims, raised where an
    #: overlapping survey contradicts them.
    accuracy_m: float
    #: None for a file that failed.
    accuracy_source: Optional[AccuracySource]
    samples: int
    patches: int
    crs: int
    conflicts: List[Conflict]
    #: The survey's own CRS ("EPSG:n", or a WKT 2 definition), the vertical CRS its file
    #: named ("unknown" where none), and what converting its heights added to ε.
    crs_key: str = ""
    vertical_crs: str = ""
    vertical_error_m: float = 0.0
    #: The median and 90th percentile of its kernels' ε as served, and the largest it claims
    #: itself.
    accuracy_median_m: float = 0.0
    accuracy_p90_m: float = 0.0
    claimed_accuracy_m: float = 0.0


@dataclass(frozen=True)
class IngestResult:
    source: str
    #: Inserted, replaced, unchanged or failed.
    outcome: Outcome
    survey: str
    error: str
    samples: int
    seconds: float
    conflicts: List[Conflict]
    #: Why the file failed, as a kind to branch on ("NOT_A_DEM", "CRS_CONFLICT", …, the
    #: proto's ErrorReason without its prefix); "" unless it failed.
    reason: str = ""


@dataclass(frozen=True)
class ChangeEvent:
    #: Inserted, replaced, retired or failed.
    kind: Outcome
    survey: str
    source: str
    error: str
    at_unix: int
    conflicts: List[Conflict]
    #: Where the terrain changed, (west, south, east, north) in degrees; None for a failure.
    changed: Optional[Tuple[float, float, float, float]] = None
    #: The HTTP server's tiles this invalidates, one (z, x0, y0, x1, y1) range per level from 0
    #: to 24: Web Mercator XYZ raster tiles, and Cesium's geographic TMS terrain tiles.
    web_tiles: List[Tuple[int, int, int, int, int]] = field(default_factory=list)
    terrain_tiles: List[Tuple[int, int, int, int, int]] = field(default_factory=list)


@dataclass(frozen=True)
class ViewStep:
    """What one camera changed: the patches added and the ids removed, and the whole cut's
    size. The session's ``patches`` holds the cut once the step is applied."""

    frame: int
    added: List[Patch]
    removed: List[int]
    patches: int
    #: The step's messages as they crossed the wire, bytes.
    wire_bytes: int
    #: Patches the cut took back from the session's cache, by id: not sent again.
    restored: List[int] = field(default_factory=list)
    #: Patches sent ahead for the cameras the daemon predicts next, now in the cache.
    prefetched: List[Patch] = field(default_factory=list)


def _message_dataclass(name: str, message) -> type:
    """A frozen dataclass with a message's fields, so that replies with many plain fields
    stay in step with the proto."""
    return make_dataclass(
        name, [(f.name, object) for f in message.DESCRIPTOR.fields], frozen=True
    )


def _from_message(cls, m):
    return cls(**{f.name: getattr(m, f.name) for f in fields(cls)})


Stats = _message_dataclass("Stats", admin_pb2.StatsReply)
VerifyResult = _message_dataclass("VerifyResult", admin_pb2.VerifyReply)
CompactResult = _message_dataclass("CompactResult", admin_pb2.CompactReply)
RetireResult = _message_dataclass("RetireResult", admin_pb2.RetireReply)


_DISTRUSTED = {admin_pb2.DISTRUSTED_THIS: "this", admin_pb2.DISTRUSTED_OTHER: "other",
               admin_pb2.DISTRUSTED_BOTH: "both"}


def _conflict(c) -> Conflict:
    has = c.HasField("shift")
    return Conflict(survey=c.survey, max_m=c.max_m, rms_m=c.rms_m,
                    shift_m=(c.shift.east_m, c.shift.north_m, c.shift.up_m) if has else None,
                    rms_after_m=c.shift.rms_after_m if has else None,
                    turned_deg=c.shift.turned_deg if has else None,
                    scale=c.shift.scale if has else None,
                    tilt_m_per_km=(c.shift.tilt_east_m_per_km, c.shift.tilt_north_m_per_km)
                    if has else None,
                    distrusted=_DISTRUSTED.get(c.distrusted, ""),
                    decided_by=c.decided_by, statistic=c.statistic, confidence=c.confidence,
                    shift_determined=c.shift_determined, takes_tie=c.takes_tie,
                    changes=tuple(ChangeRegion(later=r.later, area_m2=r.area_m2,
                                               gained_m3=r.gained_m3, lost_m3=r.lost_m3,
                                               most_m=r.most_m, bounds=tuple(r.bounds))
                                  for r in c.changes))


def _reason(value: int) -> str:
    """An ErrorReason as its name without the prefix; "" for UNSPECIFIED."""
    if value == 0:
        return ""
    return admin_pb2.ErrorReason.Name(value).removeprefix("ERROR_REASON_")


def _conflicts(cs) -> List[Conflict]:
    return [_conflict(c) for c in cs]


def _rect(roi: Rect) -> "terrain_pb2.Rect":
    xmin, ymin, xmax, ymax = (float(v) for v in roi)
    return terrain_pb2.Rect(xmin=xmin, ymin=ymin, xmax=xmax, ymax=ymax)


class Client:
    """A connection to a Patchwork daemon.

    ``target`` is ``host:port``. ``token`` is sent as ``authorization: Bearer <token>``
    (the read token opens Terrain, the admin token everything). With ``ca`` (PEM bytes or a
    path) the channel uses TLS. ``timeout`` bounds each call, in seconds.
    """

    def __init__(self, target: str, token: Optional[str] = None, *, ca=None, timeout: float = 60.0):
        options = [
            # Tiles come in bands under gRPC's default 4 MB, but a large unary tile or a
            # large patch batch may not.
            ("grpc.max_receive_message_length", 256 << 20),
        ]
        if ca is not None:
            pem = ca if isinstance(ca, bytes) else open(ca, "rb").read()
            self._channel = grpc.secure_channel(target, grpc.ssl_channel_credentials(pem), options)
        else:
            self._channel = grpc.insecure_channel(target, options)
        self._metadata = [("authorization", f"Bearer {token}")] if token else []
        self.timeout = timeout
        self.terrain = terrain_pb2_grpc.TerrainStub(self._channel)
        self.admin = admin_pb2_grpc.AdminStub(self._channel)

    def close(self):
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *_):
        self.close()

    def _call(self, method, request, **kw):
        return method(request, timeout=self.timeout, metadata=self._metadata, **kw)

    # --- Terrain -----------------------------------------------------------------------

    def query_patches(self, roi: Rect, error: float, crs: str = "") -> List[Patch]:
        """The uniform cut over ``roi`` = (xmin, ymin, xmax, ymax) at ``error`` metres;
        ``crs`` names the ROI's CRS ("EPSG:3857", a WKT or a PROJ string; the store's by
        default). Each patch comes in its own frame, in the CRS its ``crs`` names."""
        cut = terrain_pb2.UniformCut(roi=_rect(roi), error=error)
        return self._patches(terrain_pb2.PatchQuery(uniform=cut, crs=crs))

    def query_view(self, camera: Camera) -> List[Patch]:
        """The view-dependent cut for a camera."""
        return self._patches(terrain_pb2.PatchQuery(view=camera.to_proto()))

    def _patches(self, q) -> List[Patch]:
        out = []
        for batch in self._call(self.terrain.QueryPatches, q):
            out.extend(Patch.from_proto(p) for p in batch.patches)
        return out

    def tile(self, roi: Rect, width: int, height: int, error: float, backend: str = "auto",
             crs: str = "", heights: str = "store") -> np.ndarray:
        """A height × width float32 tile over ``roi``, north row first, NaN for nodata. With
        ``crs`` ("EPSG:3857", a UTM zone, a WKT or a PROJ string), the ROI and the tile are in
        that CRS; the store's by default. ``heights`` says what they are measured from:
        "store" (its vertical CRS), "ellipsoid" (WGS 84's) or a vertical CRS as "EPSG:n"."""
        return self.tile_with_info(roi, width, height, error, backend, crs, heights)[0]

    def tile_with_info(self, roi: Rect, width: int, height: int, error: float, backend: str = "auto",
                       crs: str = "", heights: str = "store"):
        """:meth:`tile`, with what the daemon says of it (:class:`TileInfo`)."""
        cut = terrain_pb2.UniformCut(roi=_rect(roi), error=error)
        return self._bands(terrain_pb2.TileRequest(uniform=cut, width=width, height=height,
                                                   backend=BACKENDS[backend], crs=crs,
                                                   heights=heights))

    def view_tile(self, camera: Camera, width: int, height: int, backend: str = "auto") -> np.ndarray:
        """The view-dependent tile a camera sees: its screen grid projected onto the ground."""
        req = terrain_pb2.TileRequest(view=camera.to_proto(), width=width, height=height, backend=BACKENDS[backend])
        return self._bands(req)[0]

    def mesh(self, roi: Rect, error: float, size: int = 257, rows: int = 0, mesh_error: float = 1.0,
             skirt: float = 0.0, border: str = "shared", method: str = "rtin", hole_reach: float = 0.0,
             backend: str = "auto", crs: str = "", heights: str = "store") -> Mesh:
        """A triangle mesh of the cut's surface over ``roi`` within ``mesh_error`` metres of
        it, on a ``size`` × ``rows`` grid of vertices (``rows`` 0: square) whose corners are
        the ROI's; ``border`` "shared" keeps every border vertex, ``method`` "rtin" or
        "quadtree", skirts ``skirt`` metres deep, voids within ``hole_reach`` metres of data
        drawn over. ``crs`` names the CRS of the ROI and the vertices (the store's by
        default), ``heights`` what their heights are measured from (see :meth:`tile`)."""
        req = terrain_pb2.MeshRequest(
            cut=terrain_pb2.UniformCut(roi=_rect(roi), error=error), size=size, rows=rows,
            mesh_error=mesh_error, skirt_m=skirt, border=MESH_BORDERS[border], method=MESH_METHODS[method],
            hole_reach_m=hole_reach, backend=BACKENDS[backend], crs=crs, heights=heights,
        )
        m = self._call(self.terrain.MeshTile, req)
        r = m.roi
        col = np.asarray(m.columns, dtype=np.float64)
        row = np.asarray(m.rows, dtype=np.float64)
        vertices = np.stack([
            r.xmin + col * (r.xmax - r.xmin) / (m.size - 1),
            r.ymax - row * (r.ymax - r.ymin) / (m.grid_rows - 1),
            np.asarray(m.heights, dtype=np.float64),
        ], axis=1)
        return Mesh(
            vertices=vertices, triangles=np.asarray(m.indices, dtype=np.uint32).reshape(-1, 3),
            skirt_vertices=m.skirt_vertices, skirt_triangles=m.skirt_triangles,
            max_deviation=m.max_deviation, max_hole_reach=m.max_hole_reach_m, patches=m.patches,
            max_error=m.max_error, backend=m.backend, crs=m.crs, crs_key=m.crs_key,
        )

    def _bands(self, req):
        """TileBands put back together: each band is whole rows of f32 little-endian."""
        out, info = None, None
        for band in self._call(self.terrain.TileBands, req):
            if out is None:
                out = np.empty((band.height, band.width), dtype=np.float32)
                info = TileInfo(backend=band.backend, patches=band.patches, max_error=band.max_error,
                                crs=band.crs, crs_key=band.crs_key, vertical_crs=band.vertical_crs)
            rows = np.frombuffer(band.heights, dtype="<f4").reshape(band.rows, band.width)
            out[band.row:band.row + band.rows] = rows
        if out is None:
            raise RuntimeError("the tile came back empty")
        return out, info

    def sample(self, points, error: float, crs: str = "", heights: str = "store") -> np.ndarray:
        """Heights at points, an n × 2 array (or a sequence of (x, y)) in ``crs`` (the
        store's by default), measured from ``heights`` (see :meth:`tile`); float32, NaN where
        there is no data."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        req = terrain_pb2.SampleRequest(
            points=[terrain_pb2.Point(x=x, y=y) for x, y in pts], error=error, crs=crs,
            heights=heights,
        )
        r = self._call(self.terrain.SampleHeights, req)
        z = np.asarray(r.heights, dtype=np.float32)
        z[np.frombuffer(r.valid, dtype=np.uint8) == 0] = np.nan
        return z

    def sources(self, points, error: float, crs: str = "") -> List[Optional[dict]]:
        """What served the height at each point (see :meth:`sample`): a dict with the
        survey's ``survey`` id, its ``file``, what its sidecar says (``title``, ``license``,
        ``attribution``, ``acquired``, None where it says nothing), and the patch's ``level``,
        ``cell_m`` and ``error_m``; None where the point has no height."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        req = terrain_pb2.SampleRequest(
            points=[terrain_pb2.Point(x=x, y=y) for x, y in pts], error=error, crs=crs,
            sources=True,
        )
        r = self._call(self.terrain.SampleHeights, req)
        given = lambda v: v or None  # noqa: E731
        out: List[Optional[dict]] = []
        for s in r.sources:
            if not s.survey:
                out.append(None)
                continue
            a = s.about
            out.append(dict(survey=s.survey, file=s.file, title=given(a.title), license=given(a.license),
                            attribution=given(a.attribution), acquired=given(a.acquired), level=s.level,
                            cell_m=s.cell_m, error_m=s.error_m))
        return out

    def view_session(self, cache_bytes: int = 0, prefetch_bytes: int = 0) -> "ViewSession":
        """A view session: send cameras with :meth:`ViewSession.update`, and the session's
        ``patches`` follow the view cut, by the difference from one camera to the next.

        ``cache_bytes`` keeps that many bytes of patches beyond the cut (those that left it,
        and those prefetched), so that the daemon need not send them again when they come back
        into view; ``prefetch_bytes`` lets each step send that many bytes more of the patches
        the daemon predicts the next cameras will need (constant velocity and turn rate)."""
        return ViewSession(self, cache_bytes, prefetch_bytes)

    def subscribe(self) -> Iterator[ChangeEvent]:
        """Change events as they happen (needs the admin token where the daemon has one).
        Runs without a deadline: cancel by closing the client."""
        for e in self.terrain.Subscribe(terrain_pb2.SubscribeRequest(), metadata=self._metadata):
            ranges = lambda rs: [(r.z, r.x0, r.y0, r.x1, r.y1) for r in rs]  # noqa: E731
            changed = ((e.changed.west, e.changed.south, e.changed.east, e.changed.north)
                       if e.HasField("changed") else None)
            yield ChangeEvent(kind=_OUTCOME[e.outcome], survey=f"{e.survey:016x}", source=e.source, error=e.error,
                              at_unix=e.at_unix, conflicts=_conflicts(e.conflicts), changed=changed,
                              web_tiles=ranges(e.web_tiles), terrain_tiles=ranges(e.terrain_tiles))

    # --- Admin -------------------------------------------------------------------------

    def ingest(self, paths: Sequence[str], accuracy_m: Optional[float] = None) -> List[IngestResult]:
        req = admin_pb2.IngestRequest(paths=list(paths))
        if accuracy_m is not None:
            req.accuracy_m = accuracy_m
        # Ingest takes as long as the files need.
        r = self.admin.Ingest(req, metadata=self._metadata)
        return [IngestResult(source=i.source, outcome=_OUTCOME[i.outcome], survey=f"{i.survey:016x}", error=i.error,
                             samples=i.samples, seconds=i.seconds, conflicts=_conflicts(i.conflicts),
                             reason=_reason(i.reason))
                for i in r.results]

    def surveys(self) -> List[Survey]:
        r = self._call(self.admin.ListSurveys, admin_pb2.ListSurveysRequest())
        return [Survey(id=s.id, source=s.source, status=_STATUS[s.status], error=s.error, accuracy_m=s.accuracy_m,
                       accuracy_source=_ACCURACY_SOURCE.get(s.accuracy_source), samples=s.samples, patches=s.patches, crs=s.crs,
                       conflicts=_conflicts(s.conflicts), crs_key=s.crs_key, vertical_crs=s.vertical_crs,
                       vertical_error_m=s.vertical_error_m, accuracy_median_m=s.accuracy_median_m,
                       accuracy_p90_m=s.accuracy_p90_m, claimed_accuracy_m=s.claimed_accuracy_m)
                for s in r.surveys]

    def retire(self, id_or_source: str):
        return _from_message(RetireResult, self.admin.Retire(
            admin_pb2.RetireRequest(id_or_source=id_or_source), metadata=self._metadata))

    def forget(self, source: str) -> None:
        self._call(self.admin.Forget, admin_pb2.ForgetRequest(source=source))

    def stats(self):
        """The store's figures; ``ingesting_phase`` is an :class:`IngestPhase`, None when no
        ingest is under way."""
        s = _from_message(Stats, self._call(self.admin.Stats, admin_pb2.StatsRequest()))
        return replace(s, ingesting_phase=_PHASE.get(s.ingesting_phase))

    def verify(self):
        return _from_message(VerifyResult, self.admin.Verify(admin_pb2.VerifyRequest(), metadata=self._metadata))

    def compact(self):
        return _from_message(CompactResult, self.admin.Compact(admin_pb2.CompactRequest(), metadata=self._metadata))


class ViewSession:
    """One bidirectional ViewSession stream. ``patches`` maps id to :class:`Patch`: after
    each :meth:`update` it is the view cut for that camera. ``cache`` holds the patches kept
    beyond it, evicted by the rule the daemon follows (proto ``ViewDelta``): a patch leaving
    the cut, then each prefetched one, goes in last; a patch taken back into the cut leaves;
    the first in go until the rest fit in ``cache_bytes``, each counted at its message's
    encoded size."""

    def __init__(self, client: Client, cache_bytes: int = 0, prefetch_bytes: int = 0):
        self._cameras: "queue.Queue" = queue.Queue()
        self._replies = client.terrain.ViewSession(self._requests(), metadata=client._metadata)
        self.patches: Dict[int, Patch] = {}
        self.cache: "OrderedDict[int, Tuple[Patch, int]]" = OrderedDict()
        self.cache_bytes = cache_bytes
        self.prefetch_bytes = prefetch_bytes
        self._cached = 0
        self._sizes: Dict[int, int] = {}
        self.frame = -1

    def _requests(self):
        while True:
            cam = self._cameras.get()
            if cam is None:
                return
            yield cam

    def _put(self, p: Patch, size: int):
        self._take(p.id)
        self.cache[p.id] = (p, size)
        self._cached += size

    def _take(self, i: int):
        kept = self.cache.pop(i, None)
        if kept is not None:
            self._cached -= kept[1]
        return kept

    def update(self, camera: Camera) -> ViewStep:
        """Sends a camera and applies what the daemon says changed."""
        cut = camera.to_proto()
        cut.cache_bytes = self.cache_bytes
        cut.prefetch_bytes = self.prefetch_bytes
        self._cameras.put(cut)
        added, removed, restored, prefetched, wire, first = [], [], [], [], 0, True
        while True:
            d = next(self._replies)
            wire += d.ByteSize()
            if first:
                for i in d.removed:
                    p = self.patches.pop(i, None)
                    size = self._sizes.pop(i, 0)
                    if p is not None and self.cache_bytes > 0:
                        self._put(p, size)
                    removed.append(i)
                for i in d.restored:
                    kept = self._take(i)
                    if kept is None:
                        raise RuntimeError(f"patch {i:016x} restored but not in the cache")
                    self.patches[i], self._sizes[i] = kept
                    restored.append(i)
                first = False
            for p in d.added:
                q = Patch.from_proto(p)
                self._take(q.id)
                self.patches[q.id] = q
                self._sizes[q.id] = p.ByteSize()
                added.append(q)
            for p in d.prefetched:
                q = Patch.from_proto(p)
                self._put(q, p.ByteSize())
                prefetched.append(q)
            if d.last:
                while self._cached > self.cache_bytes and self.cache:
                    _, (_, size) = self.cache.popitem(last=False)
                    self._cached -= size
                self.frame = d.frame
                return ViewStep(frame=d.frame, added=added, removed=removed, patches=d.patches,
                                wire_bytes=wire, restored=restored, prefetched=prefetched)

    def close(self):
        self._cameras.put(None)
        self._replies.cancel()

    def __enter__(self):
        return self

    def __exit__(self, *_):
        self.close()
