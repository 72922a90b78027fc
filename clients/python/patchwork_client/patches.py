"""Patches as the daemon sends them, and Formula 1 over them with numpy.

:func:`resample` follows the daemon's CPU resampler rule for rule (docs/MODEL.md,
"Resampling"), so that a client holding a cut's patches gets the tile the daemon would give:
the same nodata mask, and heights within a millimetre (the two add the same terms in a
different order).
"""

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from ._proto import terrain_pb2 as pb

#: The i16 value that marks a void sample.
I16_VOID = -32768
#: How close to a grid line, in cells, a point counts as on it (as the daemon rounds).
SNAP = 1e-9
#: Edge patches: flag bits per sample.
VALID = 1
EDGE_CELL = 2
#: An edge patch's weight never falls below this inside its data.
MIN_WEIGHT = 1e-6

Rect = Tuple[float, float, float, float]


@dataclass(frozen=True)
class Patch:
    """One patch of a cut: a window of samples and what Formula 1 needs to blend it.

    Grid coordinates are the window's: sample (c, r) of ``samples`` (row r, column c) lies at
    ``origin + c·step_x·(cos θ, sin θ) + r·step_y·(sin θ, −cos θ)``.
    """

    id: int
    survey: int
    level: int
    #: "bilinear" (a window of one level of one survey), "bicubic" (the same in a store of C2
    #: patches: the natural bicubic spline through the samples) or "edge" (see the daemon's
    #: README).
    kind: str
    #: The patch serves errors in [error, max_error), metres.
    error: float
    max_error: float
    #: The kernel's bounds in the store's CRS: (xmin, ymin, xmax, ymax).
    bounds: Rect
    #: The frame: sample (c, r) of the window at origin + c·step_x·(cos θ, sin θ) +
    #: r·step_y·(sin ψ, −cos ψ), ψ = row_theta for a skewed or mirrored grid, else θ; in
    #: the CRS ``crs`` names (empty: the store's).
    origin: Tuple[float, float]
    theta: float
    step: Tuple[float, float]
    #: rows × cols heights, float32, NaN where void.
    samples: np.ndarray
    #: The kernel in window cells: (c0, r0, c1, r1).
    kernel: Tuple[int, int, int, int]
    #: The blend weight's support: the unclipped window's centre and half-size, in cells.
    centre: Tuple[float, float]
    half: Tuple[float, float]
    #: Edge patches: the slope of their flat-topped weight; 0 for the plain tent.
    flat: float
    #: The kernel's valid part, n × 4 rectangles (c0, r0, c1, r1) in window cells.
    valid: np.ndarray
    #: Edge patches: rows × cols flag bytes (VALID, EDGE_CELL); None for bilinear patches.
    flags: Optional[np.ndarray]
    #: Taken where nothing in the cut is as accurate as asked: blended only where no other
    #: patch of the cut covers a point.
    fallback: bool
    #: The patch's size as a protobuf message, bytes.
    wire_bytes: int
    #: Bicubic patches: the (rows + 2) × (cols + 2) B-spline coefficients of their spline.
    coef: Optional[np.ndarray] = None
    row_theta: Optional[float] = None
    #: The CRS of the frame, "EPSG:n" or a WKT 2 definition; empty for the store's.
    crs: str = ""
    #: The accurate blend's closed sides of the kernel: bit 0 its first column, bit 1 its
    #: first row, bit 2 its last column, bit 3 its last row (see :func:`resample`).
    closed: int = 0

    @staticmethod
    def from_proto(p: "pb.Patch") -> "Patch":
        rows, cols = p.rows, p.cols
        if p.encoding == pb.SAMPLE_ENCODING_I16:
            raw = np.frombuffer(p.data, dtype="<i2")
            z = (p.offset + p.scale * raw.astype(np.float64)).astype(np.float32)
            z[raw == I16_VOID] = np.nan
        else:
            z = np.frombuffer(p.data, dtype="<f4").astype(np.float32)
        if z.size != rows * cols:
            raise ValueError(f"patch {p.id:016x}: {z.size} samples for {cols} × {rows}")
        edge = p.kind == pb.PATCH_KIND_EDGE
        flags = np.frombuffer(p.flags, dtype=np.uint8).reshape(rows, cols) if edge else None
        return Patch(
            id=p.id,
            survey=p.survey,
            level=p.level,
            kind=_KINDS[p.kind],
            error=p.error,
            max_error=p.max_error,
            bounds=(p.bounds.xmin, p.bounds.ymin, p.bounds.xmax, p.bounds.ymax),
            origin=(p.frame.origin_x, p.frame.origin_y),
            theta=p.frame.theta,
            step=(p.frame.step_x, p.frame.step_y),
            samples=z.reshape(rows, cols),
            kernel=(p.kernel_c0, p.kernel_r0, p.kernel_c1, p.kernel_r1),
            centre=(p.centre_x, p.centre_y),
            half=(p.half_x, p.half_y),
            flat=p.flat,
            valid=np.array([[v.c0, v.r0, v.c1, v.r1] for v in p.valid], dtype=np.float64).reshape(-1, 4),
            flags=flags,
            fallback=p.fallback,
            wire_bytes=p.ByteSize(),
            coef=_spline_fit(z.reshape(rows, cols)) if p.kind == pb.PATCH_KIND_BICUBIC else None,
            row_theta=p.frame.row_theta if p.frame.HasField("row_theta") else None,
            crs=p.crs,
            closed=p.closed,
        )

    def to_grid(self, x: np.ndarray, y: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Window grid coordinates of points of the patch's CRS, snapped onto grid lines
        within SNAP."""
        c, s = np.cos(self.theta), np.sin(self.theta)
        dx, dy = x - self.origin[0], y - self.origin[1]
        if self.row_theta is None:
            return _snap((dx * c + dy * s) / self.step[0]), _snap((dx * s - dy * c) / self.step[1])
        # A skewed or mirrored grid: the inverse of the axes' matrix.
        vx, vy = np.sin(self.row_theta), -np.cos(self.row_theta)
        det = c * vy - s * vx
        a = (dx * vy - dy * vx) / det
        b = (c * dy - s * dx) / det
        return _snap(a / self.step[0]), _snap(b / self.step[1])

    def at(self, x: np.ndarray, y: np.ndarray, blend: str = "formula1"):
        """Weight, height and whether the patch covers each point; weight 0 where it does not
        reach, height NaN where it has none. The weight is Formula 1's, or with ``blend``
        "accurate" the accurate blend's (1 over the kernel, see :func:`resample`)."""
        gx, gy = self.to_grid(x, y)
        tx = (gx - self.centre[0]) / self.half[0]
        ty = (gy - self.centre[1]) / self.half[1]
        rows, cols = self.samples.shape
        reach = (np.abs(tx) < 1) & (np.abs(ty) < 1) & (gx >= 0) & (gy >= 0) & (gx <= cols - 1) & (gy <= rows - 1)
        if self.kind == "edge":
            z, hit_weight = _edge_eval(self.samples, self.flags, gx, gy)
        elif self.kind == "bicubic":
            # Where the bilinear patch is defined (the same validity), the spline's height.
            z = _bilinear(self.samples, gx, gy)
            z = np.where(np.isnan(z), np.nan, _spline_eval(self.coef, gx, gy))
            hit_weight = 1.0
        else:
            z, hit_weight = _bilinear(self.samples, gx, gy), 1.0
        reach &= ~np.isnan(z)
        k = self.kernel
        if blend == "accurate":
            w = (self._ramp(gx, tx, k[0], k[2], self.centre[0], self.half[0], self.closed)
                 * self._ramp(gy, ty, k[1], k[3], self.centre[1], self.half[1], self.closed >> 1)
                 * hit_weight)
        else:
            norm = 1.0 / (self.half[0] * self.step[0] * self.half[1] * self.step[1])
            w = self._weight(tx) * self._weight(ty) * norm * hit_weight
        covered = reach & (gx >= k[0]) & (gx <= k[2]) & (gy >= k[1]) & (gy <= k[3])
        return np.where(reach, w, 0.0), np.where(reach, z, np.nan), covered, reach

    def _ramp(self, g, t, k0, k1, centre, half, closed):
        """The accurate blend's weight along one axis: 1 on the kernel [k0, k1], else a ramp
        from 1 at the kernel's edge on the point's side to 0 at the window's, s for bilinear
        and edge patches and 6s⁵ − 15s⁴ + 10s³ for bicubic ones, kept below 1.

        ``closed`` holds the axis's closed sides in bits 0 (k0) and 2 (k1): beyond such a side
        the weight is 0, and inside it the same ramp runs from 0 at the side to 1 a margin in
        (the unclipped window's extension zone on that side)."""
        shape = self._shape
        edge = np.where(g < k0, k0, k1)
        tk = np.abs(edge - centre) / half
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.clip((1.0 - np.abs(t)) / (1.0 - tk), 0.0, 1.0)
        s = np.where(np.isnan(s), 0.0, s)
        outer = np.minimum(shape(s), _BELOW_ONE)
        lo, hi = bool(closed & 1), bool(closed & 4)
        outer = np.where((g < k0) & lo, 0.0, outer)
        outer = np.where((g > k1) & hi, 0.0, outer)
        inner = np.ones_like(g, dtype=np.float64)
        if lo or hi:
            s = np.ones_like(g, dtype=np.float64)
            if lo:
                s = np.minimum(s, (g - k0) / (half - abs(centre - k0)))
            if hi:
                s = np.minimum(s, (k1 - g) / (half - abs(k1 - centre)))
            inner = np.where(s >= 1.0, 1.0, np.clip(shape(s), 0.0, _BELOW_ONE))
        return np.where((g >= k0) & (g <= k1), inner, outer)

    def _shape(self, s):
        """The ramp's shape: s, or 6s⁵ − 15s⁴ + 10s³ for bicubic patches (a C2 join)."""
        return s**3 * (s * (6.0 * s - 15.0) + 10.0) if self.kind == "bicubic" else s

    def _weight(self, t: np.ndarray) -> np.ndarray:
        a = np.minimum(np.abs(t), 1.0)
        w = 1.0 - a
        if self.kind == "bicubic":
            return w**3 * (3.0 * a + 1.0)
        return np.minimum(w * self.flat, 1.0) if self.flat > 0 else w


_KINDS = {
    pb.PATCH_KIND_BILINEAR: "bilinear",
    pb.PATCH_KIND_EDGE: "edge",
    pb.PATCH_KIND_BICUBIC: "bicubic",
}


def _fill_voids(z: np.ndarray) -> np.ndarray:
    """Void samples filled, ring by ring inwards, with the mean of their valid 4-neighbours."""
    z = z.astype(np.float64)
    while np.isnan(z).any():
        p = np.pad(z, 1, constant_values=np.nan)
        near = np.stack([p[1:-1, :-2], p[1:-1, 2:], p[:-2, 1:-1], p[2:, 1:-1]])
        n = (~np.isnan(near)).sum(axis=0)
        fill = np.isnan(z) & (n > 0)
        if not fill.any():
            return np.where(np.isnan(z), 0.0, z)
        z = np.where(fill, np.nansum(near, axis=0) / np.maximum(n, 1), z)
    return z


def _fit_lines(z: np.ndarray) -> np.ndarray:
    """The natural cubic spline through each column of z (n × k), as n + 2 B-spline
    coefficients per column."""
    n = z.shape[0]
    c = np.empty((n + 2,) + z.shape[1:])
    if n == 1:
        c[:] = z[0]
        return c
    c[1:-1] = z
    if n > 2:
        m = n - 2
        a = 4.0 * np.eye(m) + np.eye(m, k=1) + np.eye(m, k=-1)
        rhs = 6.0 * z[1:-1]
        rhs[0] -= z[0]
        rhs[-1] -= z[-1]
        c[2:-2] = np.linalg.solve(a, rhs)
    c[0] = 2.0 * c[1] - c[2]
    c[-1] = 2.0 * c[-2] - c[-3]
    return c


def _spline_fit(samples: np.ndarray) -> np.ndarray:
    """The natural bicubic spline through a window's samples, voids filled for the fit: its
    (rows + 2) × (cols + 2) B-spline coefficients, the daemon's `Spline::fit`."""
    z = _fill_voids(samples)
    return _fit_lines(_fit_lines(z.T).T)


def _basis(t: np.ndarray) -> np.ndarray:
    s = 1.0 - t
    return np.stack([s**3 / 6.0, (3 * t**3 - 6 * t**2 + 4) / 6.0, (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6.0, t**3 / 6.0])


def _spline_eval(coef: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    rows, cols = coef.shape[0] - 2, coef.shape[1] - 2
    i = np.clip(np.floor(np.nan_to_num(gx)), 0, max(cols - 2, 0)).astype(np.int64)
    j = np.clip(np.floor(np.nan_to_num(gy)), 0, max(rows - 2, 0)).astype(np.int64)
    bx, by = _basis(gx - i), _basis(gy - j)
    z = np.zeros(np.shape(gx))
    for b in range(4):
        for a in range(4):
            z += by[b] * bx[a] * coef[np.minimum(j + b, rows + 1), np.minimum(i + a, cols + 1)]
    return z


def _snap(g: np.ndarray) -> np.ndarray:
    n = np.round(g)
    return np.where(np.abs(g - n) < SNAP, n, g)


def _locate(g: np.ndarray, cells: int):
    c = np.clip(np.floor(g), 0, max(cells - 1, 0)).astype(np.int64)
    return c, g - c


def _bilinear(s: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Bilinear on a cell with four valid corners; a point on a cell's edge may take the valid
    cell beside it. NaN elsewhere and outside the grid."""
    rows, cols = s.shape
    inside = (gx >= 0) & (gy >= 0) & (gx <= cols - 1) & (gy <= rows - 1)
    gx, gy = np.where(inside, gx, 0.0), np.where(inside, gy, 0.0)
    c, fx = _locate(gx, cols - 1)
    r, fy = _locate(gy, rows - 1)

    def cell(c, r, fx, fy):
        z00, z10 = s[r, c].astype(np.float64), s[r, c + 1].astype(np.float64)
        z01, z11 = s[r + 1, c].astype(np.float64), s[r + 1, c + 1].astype(np.float64)
        top = z00 + (z10 - z00) * fx
        bottom = z01 + (z11 - z01) * fx
        return top + (bottom - top) * fy

    z = cell(c, r, fx, fy)
    left, up = (fx == 0) & (c > 0), (fy == 0) & (r > 0)
    right, down = (fx == 1) & (c + 2 < cols), (fy == 1) & (r + 2 < rows)
    # Which neighbour a point may look to along each axis: left wins over right, up over down.
    beside_c = {0: True, -1: left, 1: right & ~left}
    beside_r = {0: True, -1: up, 1: down & ~up}
    # The daemon's order: columns (this, then left or right), within them rows.
    for dc in (0, -1, 1):
        for dr in (0, -1, 1):
            if dc == 0 and dr == 0:
                continue
            todo = np.isnan(z) & beside_c[dc] & beside_r[dr]
            if not todo.any():
                continue
            cc = np.clip(c + dc, 0, cols - 2)
            rr = np.clip(r + dr, 0, rows - 2)
            ffx = np.where(dc == 0, fx, 1.0 if dc < 0 else 0.0)
            ffy = np.where(dr == 0, fy, 1.0 if dr < 0 else 0.0)
            z = np.where(todo, cell(cc, rr, ffx, ffy), z)
    return np.where(inside, z, np.nan)


def _edge_eval(s: np.ndarray, flags: np.ndarray, gx: np.ndarray, gy: np.ndarray):
    """An edge patch's height and weight factor: in its edge cells, near a valid sample."""
    rows, cols = s.shape
    inside = (gx >= 0) & (gy >= 0) & (gx <= cols - 1) & (gy <= rows - 1)
    gx, gy = np.where(inside, gx, 0.0), np.where(inside, gy, 0.0)
    c, fx = _locate(gx, cols - 1)
    r, fy = _locate(gy, rows - 1)
    is_edge = (flags & EDGE_CELL) != 0
    z = np.full(gx.shape, np.nan)
    weight = np.zeros(gx.shape)
    done = ~inside
    # The daemon's order: this cell, the one above, the one to the left, the one above-left.
    candidates = [
        (c, r, fx, fy, np.ones_like(done)),
        (c, r - 1, fx, np.ones_like(fy), (fy == 0) & (r > 0)),
        (c - 1, r, np.ones_like(fx), fy, (fx == 0) & (c > 0)),
        (c - 1, r - 1, np.ones_like(fx), np.ones_like(fy), (fx == 0) & (c > 0) & (fy == 0) & (r > 0)),
    ]
    for cc, rr, ffx, ffy, allowed in candidates:
        cc, rr = np.clip(cc, 0, cols - 2), np.clip(rr, 0, rows - 2)
        take = ~done & allowed & is_edge[rr, cc]
        done |= take
        if not take.any():
            continue
        v = [(flags[rr + dy, cc + dx] & VALID) != 0 for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1))]
        zs = [s[rr + dy, cc + dx].astype(np.float64) for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1))]
        ok = take & _nearest_valid(v, ffx, ffy)
        z = np.where(ok, _cell_surface(zs, v, ffx, ffy), z)
        weight = np.where(ok, np.maximum(_ramp(v, ffx, ffy), MIN_WEIGHT), weight)
    return np.where(inside, z, np.nan), weight


def _nearest_valid(v, fx, fy):
    def side(f):
        d = f - 0.5
        on = np.abs(d) <= SNAP
        return on | (d < 0), on | (d > 0)

    x0, x1 = side(fx)
    y0, y1 = side(fy)
    return (x0 & y0 & v[0]) | (x1 & y0 & v[1]) | (x0 & y1 & v[2]) | (x1 & y1 & v[3])


def _ramp(v, fx, fy):
    r = np.ones_like(fx)
    for k in range(4):
        sx, sy = float(k & 1), float(k >> 1)
        dx = np.maximum(np.abs(fx - sx) - 0.5, 0.0)
        dy = np.maximum(np.abs(fy - sy) - 0.5, 0.0)
        r = np.where(v[k], r, np.minimum(r, 2.0 * np.maximum(dx, dy)))
    return r


def _cell_surface(z, v, fx, fy):
    """Bilinear with four valid corners, else the plane of the triangle holding the point."""
    bil = (z[0] + (z[1] - z[0]) * fx) + ((z[2] + (z[3] - z[2]) * fx) - (z[0] + (z[1] - z[0]) * fx)) * fy
    n = sum(x.astype(np.int64) for x in v)
    anti = ((n == 3) & (~v[0] | ~v[3])) | ((n == 2) & v[1] & v[2])
    anti_z = np.where(
        fx + fy <= 1.0,
        z[0] + (z[1] - z[0]) * fx + (z[2] - z[0]) * fy,
        z[3] + (z[2] - z[3]) * (1.0 - fx) + (z[1] - z[3]) * (1.0 - fy),
    )
    main_z = np.where(fx >= fy, z[0] + (z[1] - z[0]) * fx + (z[3] - z[1]) * fy, z[0] + (z[3] - z[2]) * fx + (z[2] - z[0]) * fy)
    return np.where(n == 4, bil, np.where(anti, anti_z, main_z))


def resample(patches: Sequence[Patch], roi: Rect, width: int, height: int, crs: str = "",
             blend: str = "accurate") -> np.ndarray:
    """A cut's patches blended into a height × width float32 tile over ``roi``, north row
    first, sample (i, j) at its pixel's centre, NaN where no patch covers it.

    ``blend`` is the store's (``Client.stats().blend``): "accurate" (a new store's default),
    the patches laid over one another in order of tier, error and id, each weighing 1 over its
    kernel, so that the first whose kernel holds a point ends it (docs/MODEL.md, "The accurate
    blend"), or "formula1", the weighted mean of the patches that reach a point.

    Pass every patch of the cut the tile's daemon would use (``Client.query_patches`` with the
    same ROI and error): fallback patches are ranked among themselves, so a subset can blend
    differently. A patch of a survey in another CRS than the store's (its ``crs`` set) is
    evaluated at the samples carried into its CRS, with pyproj: give the store's CRS as
    ``crs`` (``Client.stats().crs_key``).
    """
    xmin, ymin, xmax, ymax = roi
    xs = xmin + (np.arange(width) + 0.5) * ((xmax - xmin) / width)
    ys = ymax - (np.arange(height) + 0.5) * ((ymax - ymin) / height)
    carried = {}

    def in_crs(target: str):
        """The tile's samples in another CRS, once per CRS."""
        if target not in carried:
            if not crs:
                raise ValueError("a patch is in another CRS than the store's: pass the store's CRS as crs")
            import pyproj

            t = pyproj.Transformer.from_crs(pyproj.CRS(crs), pyproj.CRS(target), always_xy=True)
            X, Y = np.meshgrid(xs, ys)
            carried[target] = t.transform(X, Y)
        return carried[target]

    def points(p: Patch):
        """The tile's columns and rows the patch may reach, and its points there."""
        if p.crs:
            # Its reach is decided in its own plane, over the whole tile.
            X, Y = in_crs(p.crs)
            return (0, width, 0, height), X, Y
        i0, i1, j0, j1 = _reach(p, xs, ys)
        if i0 >= i1 or j0 >= j1:
            return None
        X, Y = np.meshgrid(xs[i0:i1], ys[j0:j1])
        return (i0, i1, j0, j1), X, Y

    # Fallback patches blend by rank of error, equal errors sharing one.
    ranks = {e: k for k, e in enumerate(sorted({p.error for p in patches if p.fallback}))}
    if blend == "accurate":
        return _over(patches, ranks, points, width, height)
    if blend != "formula1":
        raise ValueError(f"{blend!r} is not a blend: use formula1 or accurate")
    tiers = 1 + len(ranks)
    shape = (tiers, height, width)
    total, wsum = np.zeros(shape), np.zeros(shape)
    covered, present = np.zeros(shape, bool), np.zeros(shape, bool)
    for p in patches:
        where = points(p)
        if where is None:
            continue
        (i0, i1, j0, j1), X, Y = where
        w, z, cov, reach = p.at(X, Y)
        t = 1 + ranks[p.error] if p.fallback else 0
        box = (t, slice(j0, j1), slice(i0, i1))
        total[box] += np.where(reach, w * np.nan_to_num(z), 0.0)
        wsum[box] += w
        covered[box] |= cov
        present[box] |= reach

    # Where the cut's own patches cover a point they alone count; elsewhere the best rank
    # that covers it, and every better one that reaches it.
    s, ws, cov = total[0].copy(), wsum[0].copy(), covered[0].copy()
    best = np.full((height, width), tiers)
    for t in range(tiers - 1, 0, -1):
        best = np.where(covered[t], t, best)
    for t in range(1, tiers):
        add = ~covered[0] & present[t] & (t <= best)
        s += np.where(add, total[t], 0.0)
        ws += np.where(add, wsum[t], 0.0)
        cov |= add & covered[t]
    out = np.where(cov & (ws > 0), s / np.where(ws > 0, ws, 1.0), np.nan)
    return out.astype(np.float32)


def _over(patches, ranks, points, width: int, height: int) -> np.ndarray:
    """The accurate blend: each patch, in order of tier (the cut's, then each fallback rank),
    error and id, takes its weight's share of what the patches before it left at a point,
    until a patch whose kernel holds the point has taken it; patches of a worse tier than the
    first that covers a point do not count there. The first patch with a closed side whose
    kernel holds a point takes what is left there at the end (it weighs less than 1 on the
    ramp inside that side)."""
    tier_of = lambda p: 1 + ranks[p.error] if p.fallback else 0  # noqa: E731
    none = len(ranks) + 1
    total, asum = np.zeros((height, width)), np.zeros((height, width))
    rest, stop = np.ones((height, width)), np.full((height, width), none)
    hold = np.full((height, width), np.nan)
    for p in sorted(patches, key=lambda p: (tier_of(p), p.error, p.id)):
        where = points(p)
        if where is None:
            continue
        (i0, i1, j0, j1), X, Y = where
        box = (slice(j0, j1), slice(i0, i1))
        w, z, cov, reach = p.at(X, Y, blend="accurate")
        t = tier_of(p)
        take = reach & (rest[box] > 0) & (t <= stop[box])
        a = np.where(take, w * rest[box], 0.0)
        total[box] += np.where(take, a * np.nan_to_num(z), 0.0)
        asum[box] += a
        rest[box] -= a
        stop[box] = np.where(take & cov, np.minimum(stop[box], t), stop[box])
        if p.closed:
            first = take & cov & np.isnan(hold[box])
            hold[box] = np.where(first, z, hold[box])
    held = (rest > 0) & ~np.isnan(hold)
    total += np.where(held, rest * np.nan_to_num(hold), 0.0)
    asum += np.where(held, rest, 0.0)
    out = np.where((stop < none) & (asum > 0), total / np.where(asum > 0, asum, 1.0), np.nan)
    return out.astype(np.float32)


#: The largest double below 1: the most weight a patch has off its kernel.
_BELOW_ONE = 1.0 - np.finfo(np.float64).eps / 2


def _reach(p: Patch, xs: np.ndarray, ys: np.ndarray):
    """The tile columns and rows that may fall inside a patch's window, with a pixel of slack."""
    rows, cols = p.samples.shape
    cx, cy = np.meshgrid([0.0, cols - 1.0], [0.0, rows - 1.0])
    c, s = np.cos(p.theta), np.sin(p.theta)
    psi = p.theta if p.row_theta is None else p.row_theta
    vx, vy = np.sin(psi), -np.cos(psi)
    wx = p.origin[0] + cx * p.step[0] * c + cy * p.step[1] * vx
    wy = p.origin[1] + cx * p.step[0] * s + cy * p.step[1] * vy
    px = abs(xs[1] - xs[0]) if len(xs) > 1 else np.inf
    py = abs(ys[1] - ys[0]) if len(ys) > 1 else np.inf
    i0 = int(np.searchsorted(xs, wx.min() - px, side="left"))
    i1 = int(np.searchsorted(xs, wx.max() + px, side="right"))
    # ys run from north to south.
    j0 = int(np.searchsorted(-ys, -(wy.max() + py), side="left"))
    j1 = int(np.searchsorted(-ys, -(wy.min() - py), side="right"))
    return i0, i1, j0, j1
