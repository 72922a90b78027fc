// Formula 1 or the accurate blend on the GPU: the same sums as `cpu::blend`, one invocation per
// output sample, one
// workgroup per BLOCK × BLOCK block of samples, visiting only the patches that meet the block.
// The CPU bins patches into squares of SUPER × SUPER blocks; a first dispatch (`bin_blocks`)
// tests each bin's patches against each of its blocks' bounds and lists those that meet it,
// in the bin's order, which is the CPU's, so the sums are formed in the same order. Where a set holds fallback patches, a first pass over the bin finds the tier that serves the
// sample (see `cpu.rs`) and the second blends that tier.
//
// Positions are (hi, lo) f32 pairs relative to a tile origin (one origin per plane: a
// sample's positions in the CRSs of surveys of other CRSs follow the store plane's), and grid
// coordinates are formed as (hi, lo) pairs with error-free sums and products: they carry about
// 48 bits, so that the cell, the position inside it and the side of every edge test come out
// as with f64. A north-up grid's positions are its axes; any other grid's are made here
// (`place_points`) from a view's rows, or through a CRS lattice kept on the device, in the
// same double-f32 arithmetic, unless the CPU lists them.
// Heights arrive relative to a per-patch base, and the blend is formed relative to the base
// of the first patch that contributed: f32 then only ever holds height differences, until
// the base is added back once at the end.

// Samples at or above this are void, as are sample points whose x is.
const VOID: f32 = 3.0e38;

const KIND_BILINEAR: u32 = 0u;
const KIND_EDGE: u32 = 1u;
const KIND_BICUBIC: u32 = 2u;

// Edge patches store a flag word per sample after their heights, as a small whole number.
const FLAG_VALID: u32 = 1u;
const FLAG_EDGE_CELL: u32 = 2u;

// Set in `Use::rank` for a fallback patch.
const FALLBACK: u32 = 0x80000000u;

// Blocks along each side of a bin (`SUPER` in `mod.rs`).
const SUPER: u32 = 8u;

// `edge::MIN_WEIGHT`.
const MIN_WEIGHT: f32 = 1e-6;

// Grid coordinates this close to a line are put on it, as `ResolvedPatch::to_grid` does.
const SNAP: f32 = 1e-9;

struct Params {
    width: u32,
    height: u32,
    blocks_x: u32,
    has_fallback: u32,
    // 1 where the store plane's positions are a north-up grid's axes: `points` then holds
    // each column's x (as x hi, 0, x lo, 0), then each row's y (0, y hi, 0, y lo).
    axes: u32,
    // Bins along a row of them.
    supers_x: u32,
    // What `place_points` makes the positions from: SOURCE_AXES or SOURCE_ROWS.
    source: u32,
    // 1 where lattice 0 carries the source's positions into the store's plane.
    carry: u32,
    // The request's origin in the store's plane, as hi + lo.
    origin_hi: vec2<f32>,
    origin_lo: vec2<f32>,
    // How far patch bounds are widened before a block is tested against them.
    pad: f32,
    // Planes other than the store's whose positions `place_points` makes, each through the
    // lattice after the carry's (if any), and where the first one's start in `points`.
    planes: u32,
    plane0: u32,
    // BLEND_ACCURATE for the accurate blend, else Formula 1.
    blend: u32,
}

const BLEND_ACCURATE: u32 = 1u;

// A lattice of a transformation between two CRSs (`Reprojection`), as one request reads it:
// its nodes' images kept in `nodes`, 16 × 16 a block, found through `refs`.
struct Lattice {
    // The fraction of a node spacing at which the positions it reads have their origin S:
    // S/h − floor(S/h), per axis, as hi + lo.
    g_hi: vec2<f32>,
    g_lo: vec2<f32>,
    // 1/h, as hi + lo.
    inv_h_hi: f32,
    inv_h_lo: f32,
    // Its blocks' entries in `refs`, row-major, `width` × `height` of them.
    table: u32,
    width: u32,
    height: u32,
    _pad: u32,
    // The node of floor(S/h), counted from the first node of the table's first block.
    first: vec2<i32>,
}

// One block of a request's lattice: where its nodes are in `nodes` (NO_SLOT where it has
// none), and its anchor (the node its nodes are stored relative to) relative to the origin of
// the plane the lattice carries to, as hi + lo.
struct BlockRef {
    anchor_hi: vec2<f32>,
    anchor_lo: vec2<f32>,
    slot: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

// A patch as kept on the device, beside its samples. Grid coordinates below are local to the
// patch's uploaded samples: the window grown by one cell where the level has one, because
// the edge rule may look at the cell beyond the window.
struct Patch {
    // The patch's reach in the store's plane (min x, min y, max x, max y), hi + lo.
    bounds_hi: vec4<f32>,
    bounds_lo: vec4<f32>,
    // The column and row axes divided by the spacing: grid coordinate = dot(axis, d).
    col_hi: vec2<f32>,
    col_lo: vec2<f32>,
    row_hi: vec2<f32>,
    row_lo: vec2<f32>,
    centre: vec2<f32>,
    inv_half: vec2<f32>,
    // (c0, r0, c1, r1), closed, in local grid coordinates.
    window: vec4<f32>,
    kernel: vec4<f32>,
    base: f32,
    // `ResolvedPatch::flat`: 0 for the tent, else the slope of a weight flat on the kernel.
    flat: f32,
    offset: u32,
    cols: u32,
    rows: u32,
    kind: u32,
    // `ResolvedPatch::closed`: the kernel's sides the accurate blend does not reach across,
    // bit 0 the first column, 1 the first row, 2 the last column, 3 the last row.
    closed: u32,
    _pad2: u32,
}

// What a request adds to a patch.
struct Use {
    // World position of the first uploaded sample minus the plane's origin, as hi + lo.
    origin_hi: vec2<f32>,
    origin_lo: vec2<f32>,
    // The patch's record in `patches`.
    slot: u32,
    // Rank among the fallback patches, with FALLBACK set for a fallback patch.
    rank: u32,
    norm: f32,
    // Where the positions of the patch's plane start in `points`: 0 for the store's plane.
    points: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> patches: array<Patch>;
@group(0) @binding(3) var<storage, read> samples: array<f32>;
// Bins of SUPER × SUPER blocks: indices into `uses`, ascending.
@group(0) @binding(4) var<storage, read> bin_offsets: array<u32>;
@group(0) @binding(5) var<storage, read> bins: array<u32>;
// Each sample's height as f32 bits, NaN where void.
@group(0) @binding(6) var<storage, read_write> heights: array<u32>;
@group(0) @binding(7) var<storage, read> uses: array<Use>;
// Each block's patches, written by `bin_blocks` and read by `main` (the same buffer): how
// many, then their indices into `uses`, in a region of the block's own (`list_start`).
@group(0) @binding(9) var<storage, read_write> lists_out: array<u32>;
@group(0) @binding(10) var<storage, read> lists: array<u32>;
// What `place_points` makes the positions from: a north-up grid's axes, laid out as in
// `points`, or two entries a row of a view, its first point (relative to the origin) and the
// step to the next, (x hi, y hi, x lo, y lo) each, the first x VOID for a row without points.
@group(0) @binding(11) var<storage, read> source: array<vec4<f32>>;
@group(0) @binding(12) var<storage, read> lattices: array<Lattice>;
@group(0) @binding(13) var<storage, read> refs: array<BlockRef>;
// Lattice nodes, 256 a block: each node's offset from its block's anchor as (x hi, y hi,
// x lo, y lo), x hi VOID where the transformation has no image.
@group(0) @binding(14) var<storage, read> nodes: array<vec4<f32>>;
// [0], which no compiler can know: see `opaque`.
@group(0) @binding(16) var<storage, read> unit: array<u32>;
// `points`, written by `place_points`.
@group(0) @binding(15) var<storage, read_write> points_out: array<vec4<f32>>;

const SOURCE_AXES: u32 = 1u;
const SOURCE_ROWS: u32 = 2u;
const NO_SLOT: u32 = 0xffffffffu;
const VOID_POINT: vec4<f32> = vec4<f32>(VOID, 0.0, 0.0, 0.0);

// A quiet NaN's bits: WGSL has no NaN literal, and the bits reach the CPU as written.
const NAN_BITS: u32 = 0x7fc00000u;

// This invocation's column and row, set once in `main`.
var<private> here: vec2<u32>;

// Sample i's position in the plane whose positions start at `start`: from the axes for the
// store plane of a north-up grid (exact: each half is the split the CPU made), else its own.
fn point_at(start: u32, i: u32) -> vec4<f32> {
    if params.axes != 0u && start == 0u {
        let c = points[here.x];
        let r = points[params.width + here.y];
        return vec4<f32>(c.x, r.y, c.z, r.w);
    }
    return points[start + i];
}

// The 1-D blending weight on t in [-1, 1]: the tent, (1 - |t|)^3 (3|t| + 1) for bicubic
// patches, or for edge patches one flat on the kernel (`ResolvedPatch::weight`).
fn weight(q: Patch, t: f32) -> f32 {
    let a = min(abs(t), 1.0);
    let w = 1.0 - a;
    if q.kind == KIND_BICUBIC {
        return w * w * w * (3.0 * a + 1.0);
    }
    if q.flat > 0.0 {
        return min(w * q.flat, 1.0);
    }
    return w;
}

fn at(q: Patch, c: u32, r: u32) -> f32 {
    return samples[q.offset + r * q.cols + c];
}

// Bilinear height in one cell, as (z, 1) or (0, 0) when a corner is void.
fn in_cell(q: Patch, c: u32, r: u32, f: vec2<f32>) -> vec2<f32> {
    let z00 = at(q, c, r);
    let z10 = at(q, c + 1u, r);
    let z01 = at(q, c, r + 1u);
    let z11 = at(q, c + 1u, r + 1u);
    if max(max(z00, z10), max(z01, z11)) >= VOID {
        return vec2<f32>(0.0, 0.0);
    }
    let top = z00 + (z10 - z00) * f.x;
    let bottom = z01 + (z11 - z01) * f.x;
    return vec2<f32>(top + (bottom - top) * f.y, 1.0);
}

// `Bilinear::eval`: `Grid::bilinear_grid` inside the closed window, at the grid coordinates
// gh + gl.
fn bilinear(q: Patch, gh: vec2<f32>, gl: vec2<f32>) -> vec2<f32> {
    let w = q.window;
    if any(((gh - w.xy) + gl) < vec2<f32>(0.0)) || any(((gh - w.zw) + gl) > vec2<f32>(0.0)) {
        return vec2<f32>(0.0, 0.0);
    }
    // `Grid::locate`: a point on the last line belongs to the cell before it. The uploaded
    // samples end at the level's last line or one cell past the window, so clamping to the
    // last uploaded cell is the same rule.
    let cells = vec2<f32>(f32(q.cols - 1u), f32(q.rows - 1u));
    var cf = floor(gh);
    cf = select(cf, cf - 1.0, ((gh - cf) + gl) < vec2<f32>(0.0));
    cf = min(cf, cells - 1.0);
    let c = u32(cf.x);
    let r = u32(cf.y);
    let f = (gh - cf) + gl;
    var z = in_cell(q, c, r, f);
    if z.y > 0.0 {
        return z;
    }
    // A point on an edge shared with a valid cell uses that cell, in the CPU's order. The
    // right and lower neighbours never apply: f reaches 1 only on the level's last line.
    let left = f.x == 0.0 && c > 0u;
    let up = f.y == 0.0 && r > 0u;
    if up {
        z = in_cell(q, c, r - 1u, vec2<f32>(f.x, 1.0));
        if z.y > 0.0 {
            return z;
        }
    }
    if left {
        z = in_cell(q, c - 1u, r, vec2<f32>(1.0, f.y));
        if z.y > 0.0 {
            return z;
        }
        if up {
            z = in_cell(q, c - 1u, r - 1u, vec2<f32>(1.0, 1.0));
            if z.y > 0.0 {
                return z;
            }
        }
    }
    return vec2<f32>(0.0, 0.0);
}

// `Spline::eval`: the bicubic patch's spline at the grid coordinates gh + gl. Its
// coefficients follow the samples, (window columns + 3) per row, from the knot one before the
// window's first sample.
fn bicubic(q: Patch, gh: vec2<f32>, gl: vec2<f32>) -> f32 {
    let w = q.window;
    let n = vec2<u32>(w.zw - w.xy) + 1u;
    let x = (gh - w.xy) + gl;
    let cell = min(vec2<u32>(max(floor(x), vec2<f32>(0.0))), n - 2u);
    let t = x - vec2<f32>(cell);
    let s = 1.0 - t;
    let t2 = t * t;
    let t3 = t2 * t;
    let b0 = s * s * s / 6.0;
    let b1 = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0;
    let b2 = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0;
    let b3 = t3 / 6.0;
    let bx = vec4<f32>(b0.x, b1.x, b2.x, b3.x);
    let by = vec4<f32>(b0.y, b1.y, b2.y, b3.y);
    let stride = n.x + 2u;
    let first = q.offset + q.cols * q.rows + cell.y * stride + cell.x;
    // Summed relative to a coefficient of the cell, so that the f32 rounding scales with how
    // the surface varies near the point rather than with the patch's whole relief.
    let near = samples[first + stride + 1u];
    var z = 0.0;
    for (var b = 0u; b < 4u; b++) {
        let k = first + b * stride;
        let row = vec4<f32>(samples[k], samples[k + 1u], samples[k + 2u], samples[k + 3u]);
        z += by[b] * dot(row - near, bx);
    }
    return near + z;
}

fn flag(q: Patch, c: u32, r: u32) -> u32 {
    return u32(samples[q.offset + q.cols * q.rows + r * q.cols + c]);
}

// `edge::ramp`: twice the distance to the nearest void corner's pixel, at most 1. From the
// offset d = f − 0.5, which carries the hi/lo precision: |f − s| − 0.5 is d for s = 0 and −d
// for s = 1, so a ramp of 10⁻⁶ near a pixel edge keeps its relative precision.
fn ramp(v: vec4<bool>, d: vec2<f32>) -> f32 {
    var r = 1.0;
    for (var k = 0u; k < 4u; k++) {
        if v[k] {
            continue;
        }
        let sign = vec2<f32>(select(1.0, -1.0, (k & 1u) != 0u), select(1.0, -1.0, (k >> 1u) != 0u));
        let e = max(sign * d, vec2<f32>(0.0));
        r = min(r, 2.0 * max(e.x, e.y));
    }
    return r;
}

// `EdgeGrid::in_cell`: the surface in one edge cell as (z, weight, 1, 1), or zeros outside the
// pixels of valid corners. `d` is the point's offset from the cell's middle lines, in hi/lo
// precision, for the pixel test.
fn edge_cell(q: Patch, c: u32, r: u32, f: vec2<f32>, d: vec2<f32>) -> vec4<f32> {
    let v = vec4<bool>(
        (flag(q, c, r) & FLAG_VALID) != 0u,
        (flag(q, c + 1u, r) & FLAG_VALID) != 0u,
        (flag(q, c, r + 1u) & FLAG_VALID) != 0u,
        (flag(q, c + 1u, r + 1u) & FLAG_VALID) != 0u,
    );
    let tie = abs(d) < vec2<f32>(SNAP);
    let lo = tie | (d < vec2<f32>(0.0));
    let hi = tie | (d > vec2<f32>(0.0));
    let valid = (lo.x && lo.y && v[0]) || (hi.x && lo.y && v[1]) || (lo.x && hi.y && v[2])
        || (hi.x && hi.y && v[3]);
    if !valid {
        return vec4<f32>(0.0);
    }
    let z00 = at(q, c, r);
    let z10 = at(q, c + 1u, r);
    let z01 = at(q, c, r + 1u);
    let z11 = at(q, c + 1u, r + 1u);
    let n = u32(v[0]) + u32(v[1]) + u32(v[2]) + u32(v[3]);
    var z: f32;
    if n == 4u {
        let top = z00 + (z10 - z00) * f.x;
        let bottom = z01 + (z11 - z01) * f.x;
        z = top + (bottom - top) * f.y;
    } else if (n == 3u && (!v[0] || !v[3])) || (n == 2u && v[1] && v[2]) {
        if f.x + f.y <= 1.0 {
            z = z00 + (z10 - z00) * f.x + (z01 - z00) * f.y;
        } else {
            z = z11 + (z01 - z11) * (1.0 - f.x) + (z10 - z11) * (1.0 - f.y);
        }
    } else if f.x >= f.y {
        z = z00 + (z10 - z00) * f.x + (z11 - z10) * f.y;
    } else {
        z = z00 + (z11 - z01) * f.x + (z01 - z00) * f.y;
    }
    return vec4<f32>(z, max(ramp(v, d), MIN_WEIGHT), 1.0, 1.0);
}

fn is_edge(q: Patch, c: u32, r: u32) -> bool {
    return (flag(q, c, r) & FLAG_EDGE_CELL) != 0u;
}

// `EdgeGrid::eval` at the grid coordinates gh + gl: (z, weight, 1, 1), or zeros outside every
// edge cell and every valid pixel.
fn edge(q: Patch, gh: vec2<f32>, gl: vec2<f32>) -> vec4<f32> {
    let cells = vec2<f32>(f32(q.cols - 1u), f32(q.rows - 1u));
    if any((gh + gl) < vec2<f32>(0.0)) || any(((gh - cells) + gl) > vec2<f32>(0.0)) {
        return vec4<f32>(0.0);
    }
    var cf = floor(gh);
    cf = select(cf, cf - 1.0, ((gh - cf) + gl) < vec2<f32>(0.0));
    cf = min(cf, cells - 1.0);
    let c = u32(cf.x);
    let r = u32(cf.y);
    let f = (gh - cf) + gl;
    let d = ((gh - cf) - 0.5) + gl;
    if is_edge(q, c, r) {
        return edge_cell(q, c, r, f, d);
    }
    let left = f.x == 0.0 && c > 0u;
    let up = f.y == 0.0 && r > 0u;
    if up && is_edge(q, c, r - 1u) {
        return edge_cell(q, c, r - 1u, vec2<f32>(f.x, 1.0), vec2<f32>(d.x, 0.5));
    }
    if left {
        if is_edge(q, c - 1u, r) {
            return edge_cell(q, c - 1u, r, vec2<f32>(1.0, f.y), vec2<f32>(0.5, d.y));
        }
        if up && is_edge(q, c - 1u, r - 1u) {
            return edge_cell(q, c - 1u, r - 1u, vec2<f32>(1.0, 1.0), vec2<f32>(0.5, 0.5));
        }
    }
    return vec4<f32>(0.0);
}

fn in_kernel(q: Patch, gh: vec2<f32>, gl: vec2<f32>) -> bool {
    let k = q.kernel;
    return all(((gh - k.xy) + gl) >= vec2<f32>(0.0)) && all(((gh - k.zw) + gl) <= vec2<f32>(0.0));
}

// The accurate blend's 1-D weight along one axis (`ResolvedPatch::axis_weight`): 1 where the
// coordinate g = gh + gl lies in the kernel [k0, k1] (but on the ramp inside a closed side,
// `ResolvedPatch::inner_weight`), else 0 beyond a closed side (`axis` picks the bits of
// `q.closed`), else a ramp from the kernel's edge on its side to the unclipped window's edge,
// s for bilinear and edge patches and the C2 6s⁵ − 15s⁴ + 10s³ for bicubic ones.
fn accurate_weight(q: Patch, axis: u32, gh: f32, gl: f32, k0: f32, k1: f32, centre: f32, inv_half: f32, t: f32) -> f32 {
    let below = (gh - k0) + gl;
    let above = (gh - k1) + gl;
    if below >= 0.0 && above <= 0.0 {
        let sides = (q.closed >> axis) & 5u;
        if sides == 0u {
            return 1.0;
        }
        let half = 1.0 / inv_half;
        var s = 1.0;
        if (sides & 1u) != 0u {
            s = min(s, below / (half - abs(k0 - centre)));
        }
        if (sides & 4u) != 0u {
            s = min(s, -above / (half - abs(k1 - centre)));
        }
        if s >= 1.0 {
            return 1.0;
        }
        var v = s;
        if q.kind == KIND_BICUBIC {
            v = s * s * s * (s * (6.0 * s - 15.0) + 10.0);
        }
        return clamp(v, 0.0, 0.99999994);
    }
    let side = select(axis + 2u, axis, below < 0.0);
    if (q.closed & (1u << side)) != 0u {
        return 0.0;
    }
    let edge = select(k1, k0, below < 0.0);
    let tk = abs(edge - centre) * inv_half;
    let s = clamp((1.0 - abs(t)) / (1.0 - tk), 0.0, 1.0);
    if !(s > 0.0) {
        return 0.0;
    }
    var w = s;
    if q.kind == KIND_BICUBIC {
        w = s * s * s * (s * (6.0 * s - 15.0) + 10.0);
    }
    // Below 1 off the kernel (`ResolvedPatch::axis_weight`): near the kernel's edge the ramp
    // rounds up to 1 in f32, far more often than in f64.
    return min(w, 0.99999994);
}

// The patch at grid coordinates gh + gl: (height relative to its base, weight factor,
// covered, 1), or zeros where it has none.
fn eval_patch(q: Patch, gh: vec2<f32>, gl: vec2<f32>) -> vec4<f32> {
    switch q.kind {
        case KIND_EDGE: {
            let e = edge(q, gh, gl);
            return vec4<f32>(e.x, e.y, select(0.0, 1.0, in_kernel(q, gh, gl)), e.w);
        }
        case KIND_BICUBIC: {
            let z = bilinear(q, gh, gl);
            if z.y == 0.0 {
                return vec4<f32>(0.0);
            }
            return vec4<f32>(bicubic(q, gh, gl), 1.0, select(0.0, 1.0, in_kernel(q, gh, gl)), 1.0);
        }
        case KIND_BILINEAR, default: {
            let z = bilinear(q, gh, gl);
            return vec4<f32>(z.x, 1.0, select(0.0, 1.0, in_kernel(q, gh, gl)), z.y);
        }
    }
}

// The patch's weight and answer at sample i: (weight, height, covered, reaches).
fn sample_patch(u: Use, q: Patch, i: u32) -> vec4<f32> {
    let pt = point_at(u.points, i);
    if pt.x >= VOID {
        return vec4<f32>(0.0);
    }
    let sx = two_sum(pt.x, -u.origin_hi.x);
    let sy = two_sum(pt.y, -u.origin_hi.y);
    let dh = vec2<f32>(sx.x, sy.x);
    let dl = vec2<f32>(sx.y, sy.y) + (pt.zw - u.origin_lo);
    let cx = coord(dh, dl, q.col_hi, q.col_lo);
    let cy = coord(dh, dl, q.row_hi, q.row_lo);
    var gh = vec2<f32>(cx.x, cy.x);
    var gl = vec2<f32>(cx.y, cy.y);
    let n = round(gh);
    let on_line = abs((gh - n) + gl) < vec2<f32>(SNAP);
    gh = select(gh, n, on_line);
    gl = select(gl, vec2<f32>(0.0), on_line);
    let t = ((gh - q.centre) + gl) * q.inv_half;
    if abs(t.x) >= 1.0 || abs(t.y) >= 1.0 {
        return vec4<f32>(0.0);
    }
    let e = eval_patch(q, gh, gl);
    if e.w == 0.0 {
        return vec4<f32>(0.0);
    }
    var w: f32;
    if params.blend == BLEND_ACCURATE {
        let k = q.kernel;
        w = accurate_weight(q, 0u, gh.x, gl.x, k.x, k.z, q.centre.x, q.inv_half.x, t.x)
            * accurate_weight(q, 1u, gh.y, gl.y, k.y, k.w, q.centre.y, q.inv_half.y, t.y) * e.y;
    } else {
        w = weight(q, t.x) * weight(q, t.y) * u.norm * e.y;
    }
    return vec4<f32>(w, e.x, e.z, 1.0);
}

// Error-free transformations: a sum or product of two f32s as the rounded result and its
// exact error. Every intermediate passes through `opaque`, an integer xor with a word the
// compiler cannot know (`unit`, 0): a compiler that treats float arithmetic as real
// arithmetic (lavapipe's LLVM simplifies (a + b) − a to b, and sees through a multiplication
// by a 1.0 it cannot know) would otherwise compute every error as 0, and the double-f32
// arithmetic would silently be f32. No float algebra crosses integer operations.
fn opaque(x: f32) -> f32 {
    return bitcast<f32>(bitcast<u32>(x) ^ unit[0]);
}

// a + b exactly, as (sum, error) (Knuth).
fn two_sum(a: f32, b: f32) -> vec2<f32> {
    let s = opaque(a + b);
    let bb = opaque(s - a);
    let av = opaque(s - bb);
    return vec2<f32>(s, opaque(a - av) + opaque(b - bb));
}

// a split into two halves of 12 bits, whose products are exact in f32 (Veltkamp).
fn halves(a: f32) -> vec2<f32> {
    let c = opaque(4097.0 * a);
    let big = opaque(c - a);
    let hi = opaque(c - big);
    return vec2<f32>(hi, a - hi);
}

// a · b exactly, as (product, error), by Dekker's products of halves rather than `fma`: a
// software driver (lavapipe) evaluates fma(a, b, −a·b) unfused, as 0, which would leave
// products at f32.
fn two_prod(a: f32, b: f32) -> vec2<f32> {
    let p = opaque(a * b);
    let x = halves(a);
    let y = halves(b);
    let e0 = opaque(x.x * y.x - p);
    let e1 = opaque(e0 + x.x * y.y);
    let e2 = opaque(e1 + x.y * y.x);
    return vec2<f32>(p, e2 + x.y * y.y);
}

// dot(d, axis) for d = dh + dl and axis = ah + al, as (hi, lo).
fn coord(dh: vec2<f32>, dl: vec2<f32>, ah: vec2<f32>, al: vec2<f32>) -> vec2<f32> {
    let px = two_prod(dh.x, ah.x);
    let py = two_prod(dh.y, ah.y);
    let s = two_sum(px.x, py.x);
    let lo = s.y + px.y + py.y + (dh.x * al.x + dh.y * al.y) + (dl.x * ah.x + dl.y * ah.y);
    return two_sum(s.x, lo);
}

// x widened outwards by a few units in its last place and by params.pad.
fn widen(b: vec4<f32>) -> vec4<f32> {
    let m = abs(b) * 1e-6 + params.pad;
    return vec4<f32>(b.xy - m.xy, b.zw + m.zw);
}

// hi + lo − the origin, as one f32.
fn from_origin(hi: vec2<f32>, lo: vec2<f32>) -> vec2<f32> {
    let sx = two_sum(hi.x, -params.origin_hi.x);
    let sy = two_sum(hi.y, -params.origin_hi.y);
    return vec2<f32>(sx.x, sy.x) + (vec2<f32>(sx.y, sy.y) + (lo - params.origin_lo));
}

// The bounds of block w's points relative to the origin, widened: from the axes of a
// north-up grid (its first and last column and row, as the CPU's `block_bounds`), else from
// its points. Empty (min > max) for a block without a valid point.
fn bounds_of_block(w: vec2<u32>) -> vec4<f32> {
    if params.axes != 0u {
        let i0 = w.x * 16u;
        let i1 = min(i0 + 15u, params.width - 1u);
        let j0 = params.width + w.y * 16u;
        let j1 = params.width + min(w.y * 16u + 15u, params.height - 1u);
        let xa = points[i0].x + points[i0].z;
        let xb = points[i1].x + points[i1].z;
        let ya = points[j0].y + points[j0].w;
        let yb = points[j1].y + points[j1].w;
        return widen(vec4<f32>(min(xa, xb), min(ya, yb), max(xa, xb), max(ya, yb)));
    }
    var lo = vec2<f32>(VOID);
    var hi = vec2<f32>(-VOID);
    for (var j = w.y * 16u; j < min(w.y * 16u + 16u, params.height); j++) {
        for (var i = w.x * 16u; i < min(w.x * 16u + 16u, params.width); i++) {
            let p = points[j * params.width + i];
            if p.x >= VOID {
                continue;
            }
            let v = p.xy + p.zw;
            lo = min(lo, v);
            hi = max(hi, v);
        }
    }
    if lo.x > hi.x {
        return vec4<f32>(1.0, 1.0, 0.0, 0.0);
    }
    return widen(vec4<f32>(lo, hi));
}

// Whether the patch of use k may reach a point of the block: its reach (`ResolvedPatch::reach`),
// widened by the rounding of forming it here, meets the block's bounds. A superset of the
// CPU's test, which is harmless: a patch reaches no point outside its reach.
fn meets(k: u32, b: vec4<f32>) -> bool {
    let q = patches[uses[k].slot];
    let lo = from_origin(q.bounds_hi.xy, q.bounds_lo.xy);
    let hi = from_origin(q.bounds_hi.zw, q.bounds_lo.zw);
    let p = widen(vec4<f32>(lo, hi));
    return all(p.xy <= b.zw) && all(b.xy <= p.zw);
}

// Bin s holds entries first..end of `bins`. Each of its blocks has room for all of them and
// their count: the bins before it take SUPER² · (first + s) words.
fn list_start(w: vec2<u32>, s: u32, first: u32, end: u32) -> u32 {
    let local = (w.y % SUPER) * SUPER + w.x % SUPER;
    return SUPER * SUPER * (first + s) + local * (1u + end - first);
}

fn bin_of(w: vec2<u32>) -> u32 {
    return (w.y / SUPER) * params.supers_x + w.x / SUPER;
}

// One invocation a block: the patches of its bin whose bounds meet the block's, in order.
@compute @workgroup_size(64, 1, 1)
fn bin_blocks(@builtin(global_invocation_id) gid: vec3<u32>) {
    let blocks_y = (params.height + 15u) / 16u;
    if gid.x >= params.blocks_x * blocks_y {
        return;
    }
    let w = vec2<u32>(gid.x % params.blocks_x, gid.x / params.blocks_x);
    let s = bin_of(w);
    let first = bin_offsets[s];
    let end = bin_offsets[s + 1u];
    let start = list_start(w, s, first, end);
    let b = bounds_of_block(w);
    var n = 0u;
    if b.x <= b.z {
        for (var k = first; k < end; k++) {
            if meets(bins[k], b) {
                n++;
                lists_out[start + n] = bins[k];
            }
        }
    }
    lists_out[start] = n;
}

@compute @workgroup_size(16, 16, 1)
fn main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(workgroup_id) wid: vec3<u32>,
) {
    if gid.x >= params.width || gid.y >= params.height {
        return;
    }
    let i = gid.y * params.width + gid.x;
    here = gid.xy;
    heights[i] = NAN_BITS;
    if point_at(0u, i).x >= VOID {
        return;
    }
    let s = bin_of(wid.xy);
    let start = list_start(wid.xy, s, bin_offsets[s], bin_offsets[s + 1u]);
    let first = start + 1u;
    let end = first + lists[start];
    if params.blend == BLEND_ACCURATE {
        over(i, first, end);
        return;
    }
    // The tier: whether a cut patch covers the sample, else the best fallback rank that does.
    var cut_covers = false;
    var best = 0xffffffffu;
    if params.has_fallback != 0u {
        for (var b = first; b < end; b++) {
            let u = uses[lists[b]];
            let sp = sample_patch(u, patches[u.slot], i);
            if sp.w == 0.0 || sp.z == 0.0 {
                continue;
            }
            if (u.rank & FALLBACK) == 0u {
                cut_covers = true;
            } else {
                best = min(best, u.rank & ~FALLBACK);
            }
        }
    }
    var sum = 0.0;
    var wsum = 0.0;
    var covered = false;
    var have_ref = false;
    var zref = 0.0;
    for (var b = first; b < end; b++) {
        let u = uses[lists[b]];
        if (u.rank & FALLBACK) != 0u && (cut_covers || (u.rank & ~FALLBACK) > best) {
            continue;
        }
        let q = patches[u.slot];
        let sp = sample_patch(u, q, i);
        if sp.w == 0.0 {
            continue;
        }
        if !have_ref {
            zref = q.base;
            have_ref = true;
        }
        sum += sp.x * (sp.y + (q.base - zref));
        wsum += sp.x;
        covered = covered || sp.z != 0.0;
    }
    if covered && wsum > 0.0 {
        // One rounding of the exact sum, as the CPU's f64 sum rounded to f32.
        heights[i] = bitcast<u32>(zref + sum / wsum);
    }
}

// The accurate blend at sample i (`cpu::over_by`): the block's patches, in the set's order
// (tier, error, id), each laid under those before it with its weight's share of what they
// left, until one whose kernel holds the sample takes the rest or a worse tier comes. The
// first patch with a closed side whose kernel holds the sample takes what is left at the end
// (`cpu::Over::hold`).
fn over(i: u32, first: u32, end: u32) {
    var sum = 0.0;
    var asum = 0.0;
    var rest = 1.0;
    var stop = 0xffffffffu;
    var have_ref = false;
    var zref = 0.0;
    var holding = false;
    var hold = 0.0;
    for (var b = first; b < end; b++) {
        let u = uses[lists[b]];
        let tier = select(0u, 1u + (u.rank & ~FALLBACK), (u.rank & FALLBACK) != 0u);
        if !(rest > 0.0) || tier > stop {
            break;
        }
        let q = patches[u.slot];
        let sp = sample_patch(u, q, i);
        if sp.w == 0.0 {
            continue;
        }
        if !have_ref {
            zref = q.base;
            have_ref = true;
        }
        let a = sp.x * rest;
        sum += a * (sp.y + (q.base - zref));
        asum += a;
        rest -= a;
        if sp.z != 0.0 {
            stop = min(stop, tier);
            if q.closed != 0u && !holding {
                hold = sp.y + (q.base - zref);
                holding = true;
            }
        }
    }
    if holding && rest > 0.0 {
        sum += rest * hold;
        asum += rest;
    }
    if stop != 0xffffffffu && asum > 0.0 {
        heights[i] = bitcast<u32>(zref + sum / asum);
    }
}

// Double-f32 arithmetic on (hi, lo) pairs, for positions carried through a lattice: about 44
// bits at every step, where the CPU's f64 has 53 and f32 24.

// a + b for |a| ≥ |b| or a = 0, as (sum, error).
fn quick_two_sum(a: f32, b: f32) -> vec2<f32> {
    let s = opaque(a + b);
    return vec2<f32>(s, b - opaque(s - a));
}

fn df_add(a: vec2<f32>, b: vec2<f32>) -> vec2<f32> {
    let s = two_sum(a.x, b.x);
    let t = two_sum(a.y, b.y);
    let u = quick_two_sum(s.x, opaque(s.y + t.x));
    return quick_two_sum(u.x, opaque(u.y + t.y));
}

fn df_sub(a: vec2<f32>, b: vec2<f32>) -> vec2<f32> {
    return df_add(a, -b);
}

fn df_mul(a: vec2<f32>, b: vec2<f32>) -> vec2<f32> {
    let p = two_prod(a.x, b.x);
    return quick_two_sum(p.x, p.y + (a.x * b.y + a.y * b.x));
}

fn df_scale(a: vec2<f32>, k: f32) -> vec2<f32> {
    let p = two_prod(a.x, k);
    return quick_two_sum(p.x, p.y + a.y * k);
}

// The Catmull-Rom weights of the four nodes around a point a fraction t of the way between
// the middle two (`lattice::weights`).
fn cr_weights(t: vec2<f32>) -> array<vec2<f32>, 4> {
    let t2 = df_mul(t, t);
    let t3 = df_mul(t2, t);
    let w0 = df_add(df_add(-t3, df_scale(t2, 2.0)), -t);
    let w1 = df_add(df_add(df_scale(t3, 3.0), df_scale(t2, -5.0)), vec2<f32>(2.0, 0.0));
    let w2 = df_add(df_add(df_scale(t3, -3.0), df_scale(t2, 4.0)), t);
    let w3 = df_add(t3, -t2);
    return array<vec2<f32>, 4>(0.5 * w0, 0.5 * w1, 0.5 * w2, 0.5 * w3);
}

// The lattice cell holding u (in node spacings) as (cell, fraction hi, fraction lo), the
// fraction in [0, 1).
fn cell_of(u: vec2<f32>) -> vec3<f32> {
    var c = floor(u.x);
    var f = two_sum(u.x - c, u.y);
    if f.x < 0.0 {
        c -= 1.0;
        f = df_add(f, vec2<f32>(1.0, 0.0));
    } else if f.x >= 1.0 {
        c += 1.0;
        f = df_add(f, vec2<f32>(-1.0, 0.0));
    }
    return vec3<f32>(c, f);
}

// Lattice node (ix, iy), counted from the first node of the table, relative to the origin
// of the plane the lattice carries to; VOID_POINT where it has no image.
fn node_at(l: Lattice, ix: i32, iy: i32) -> vec4<f32> {
    if ix < 0 || iy < 0 {
        return VOID_POINT;
    }
    let b = vec2<u32>(u32(ix) / 16u, u32(iy) / 16u);
    if b.x >= l.width || b.y >= l.height {
        return VOID_POINT;
    }
    let r = refs[l.table + b.y * l.width + b.x];
    if r.slot == NO_SLOT {
        return VOID_POINT;
    }
    let d = nodes[r.slot * 256u + (u32(iy) % 16u) * 16u + u32(ix) % 16u];
    if d.x >= VOID {
        return VOID_POINT;
    }
    let x = df_add(vec2<f32>(r.anchor_hi.x, r.anchor_lo.x), vec2<f32>(d.x, d.z));
    let y = df_add(vec2<f32>(r.anchor_hi.y, r.anchor_lo.y), vec2<f32>(d.y, d.w));
    return vec4<f32>(x.x, y.x, x.y, y.y);
}

// Position p carried by lattice k (`Reprojection::at`): the tensor Catmull-Rom cubic through
// the 4 × 4 nodes around it, summed as offsets from the cell's first node as the CPU sums
// them; VOID_POINT where a node has no image.
fn carry(k: u32, p: vec4<f32>) -> vec4<f32> {
    if p.x >= VOID {
        return VOID_POINT;
    }
    let l = lattices[k];
    let ih = vec2<f32>(l.inv_h_hi, l.inv_h_lo);
    let cx = cell_of(df_add(vec2<f32>(l.g_hi.x, l.g_lo.x), df_mul(vec2<f32>(p.x, p.z), ih)));
    let cy = cell_of(df_add(vec2<f32>(l.g_hi.y, l.g_lo.y), df_mul(vec2<f32>(p.y, p.w), ih)));
    var wx = cr_weights(cx.yz);
    var wy = cr_weights(cy.yz);
    let ix = i32(cx.x) + l.first.x - 1;
    let iy = i32(cy.x) + l.first.y - 1;
    let base = node_at(l, ix + 1, iy + 1);
    if base.x >= VOID {
        return VOID_POINT;
    }
    let bx = base.xz;
    let by = base.yw;
    var ox = vec2<f32>(0.0);
    var oy = vec2<f32>(0.0);
    for (var b = 0; b < 4; b++) {
        var rx = vec2<f32>(0.0);
        var ry = vec2<f32>(0.0);
        for (var a = 0; a < 4; a++) {
            let n = node_at(l, ix + a, iy + b);
            if n.x >= VOID {
                return VOID_POINT;
            }
            rx = df_add(rx, df_mul(wx[a], df_sub(n.xz, bx)));
            ry = df_add(ry, df_mul(wx[a], df_sub(n.yw, by)));
        }
        ox = df_add(ox, df_mul(wy[b], rx));
        oy = df_add(oy, df_mul(wy[b], ry));
    }
    let x = df_add(bx, ox);
    let y = df_add(by, oy);
    return vec4<f32>(x.x, y.x, x.y, y.y);
}

// One invocation a sample: its position in the store's plane, from a view's row or through
// the carrying lattice from the axes of a grid of another CRS (unless the plane's positions
// are axes, which were copied), and in every other plane through that plane's lattice.
@compute @workgroup_size(16, 16, 1)
fn place_points(@builtin(global_invocation_id) gid: vec3<u32>) {
    if gid.x >= params.width || gid.y >= params.height {
        return;
    }
    let n = params.width * params.height;
    let col = gid.x;
    let row = gid.y;
    let i = row * params.width + col;
    var p: vec4<f32>;
    if params.source == SOURCE_ROWS {
        let first = source[2u * row];
        if first.x >= VOID {
            p = VOID_POINT;
        } else {
            let step = source[2u * row + 1u];
            let k = f32(col);
            let x = df_add(first.xz, df_scale(step.xz, k));
            let y = df_add(first.yw, df_scale(step.yw, k));
            p = vec4<f32>(x.x, y.x, x.y, y.y);
        }
    } else {
        let c = source[col];
        let r = source[params.width + row];
        p = vec4<f32>(c.x, r.y, c.z, r.w);
    }
    var next = 0u;
    if params.carry != 0u {
        p = carry(0u, p);
        next = 1u;
    }
    if params.axes == 0u {
        points_out[i] = p;
    }
    for (var k = 0u; k < params.planes; k++) {
        points_out[params.plane0 + k * n + i] = carry(next + k, p);
    }
}
