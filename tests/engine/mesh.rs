//! Meshes of uniform cuts (`MeshTile`): within their error of the resampled surface, holes
//! left open at voids, tiles of different errors that fit under their skirts, and encodings
//! that independent decoders read (tests/python/meshes.py).

use crate::common;

use patchwork::config::Config;
use patchwork::engine::{Backend, Ctx, Cut, Engine, Origin, TileRequest};
use patchwork::serve::{api, convert, proto as pb};
use patchwork_core::geom::Aabb;
use patchwork_core::mesh::{edges, encode, Mesh};
use std::path::Path;
use std::process::Command;
use std::sync::Arc;

/// An engine holding the committed crops named, each taken as exact (ε = 0), so that a cut's
/// error bounds its distance from the survey.
fn engine_with(tmp: &Path, crops: &[&str]) -> Arc<Engine> {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    let cfg = Config {
        data_dir: tmp.join("data"),
        ingest_roots: vec![data.clone()],
        ..Config::default()
    };
    let engine = Arc::new(Engine::open(cfg).unwrap());
    for c in crops {
        let done = engine
            .ingest(&data.join(c), Some(0.0), Origin::Request)
            .unwrap();
        assert!(done.error.is_empty(), "{}", done.error);
    }
    engine
}

const METHODS: [pb::MeshMethod; 2] = [pb::MeshMethod::Rtin, pb::MeshMethod::Quadtree];

#[allow(clippy::too_many_arguments)]
fn request(
    roi: &Aabb,
    error: f64,
    size: u32,
    mesh_error: f64,
    skirt: f64,
    border: pb::MeshBorder,
    method: pb::MeshMethod,
) -> pb::MeshRequest {
    pb::MeshRequest {
        crs: String::new(),
        cut: Some(pb::UniformCut {
            roi: Some(convert::rect(roi)),
            error,
        }),
        size,
        rows: 0,
        mesh_error,
        skirt_m: skirt,
        backend: pb::Backend::Cpu as i32,
        border: border as i32,
        method: method as i32,
        hole_reach_m: 0.0,
        ..Default::default()
    }
}

/// A request for a `cols × rows` grid with a shared border and no skirts.
fn shared(
    roi: &Aabb,
    error: f64,
    [cols, rows]: [u32; 2],
    mesh_error: f64,
    method: pb::MeshMethod,
) -> pb::MeshRequest {
    pb::MeshRequest {
        rows,
        ..request(
            roi,
            error,
            cols,
            mesh_error,
            0.0,
            pb::MeshBorder::Shared,
            method,
        )
    }
}

/// The mesh a request gets, as the message and as a mesh read back from it.
fn run(engine: &Engine, req: &pb::MeshRequest) -> (Mesh, pb::Mesh) {
    let ask = patchwork::serve::door::MeshAsk::try_from(req).unwrap();
    let m = api::mesh_tile(engine, &ask, &Default::default()).unwrap();
    (convert::mesh_of(&m).unwrap().0, m)
}

/// The resampled heights the mesh was made from: the same tile `MeshTile` resamples.
fn grid_heights(engine: &Engine, roi: &Aabb, error: f64, cols: usize, rows: usize) -> Vec<f32> {
    let cut = Cut::new(
        None,
        patchwork_core::mesh::pixel_roi(roi, cols, rows),
        error,
    )
    .unwrap();
    let req = TileRequest::new(cut, cols as u32, rows as u32, Backend::Cpu).unwrap();
    let (t, _, _) = engine.tile(&req, Ctx::default()).unwrap();
    t.heights
}

/// What every mesh of `h` must be: within `mesh_error` of every measured height it covers
/// (as the reply says), every cell with four measured corners covered, and no vertex drawn
/// that is void beyond `reach` cells, metres through `cell`. Returns the worst deviation
/// and the void vertices under the surface.
fn check_mesh(
    what: &str,
    m: &Mesh,
    msg: &pb::Mesh,
    h: &[f32],
    mesh_error: f64,
    reach: f64,
    cell: [f64; 2],
) -> (f64, usize) {
    let (cols, rows) = (m.cols, m.rows);
    assert_eq!(h.len(), cols * rows, "{what}");
    let got = m.surface_at_vertices();
    let measured: Vec<(usize, usize)> = (0..cols * rows)
        .filter(|&k| !h[k].is_nan())
        .map(|k| (k % cols, k / cols))
        .collect();
    let (mut worst, mut drawn_voids, mut far) = (0.0f64, 0, 0.0f64);
    for (k, (g, z)) in got.iter().zip(h).enumerate() {
        if g.is_nan() {
            continue;
        }
        if z.is_nan() {
            // A void under the surface: no farther than the reach from a measured vertex.
            let (c, r) = (k % cols, k / cols);
            let d = measured
                .iter()
                .map(|&(x, y)| {
                    ((x as f64 - c as f64) * cell[0]).hypot((y as f64 - r as f64) * cell[1])
                })
                .fold(f64::INFINITY, f64::min);
            assert!(
                d <= reach + 1e-6,
                "{what}: ({c}, {r}) drawn {d} m from data"
            );
            far = far.max(d);
            drawn_voids += 1;
        } else {
            worst = worst.max((g - *z as f64).abs());
        }
    }
    // Every cell with four measured corners is meshed: nothing measured is lost but samples
    // with no measured cell beside them.
    for r in 0..rows - 1 {
        for c in 0..cols - 1 {
            let corners = [(c, r), (c + 1, r), (c, r + 1), (c + 1, r + 1)];
            if corners.iter().all(|&(x, y)| !h[y * cols + x].is_nan()) {
                assert!(
                    corners.iter().all(|&(x, y)| !got[y * cols + x].is_nan()),
                    "{what}: cell ({c}, {r}) is not meshed"
                );
            }
        }
    }
    assert!(worst <= mesh_error + 1e-4, "{what}: {worst} > {mesh_error}");
    assert!((worst - msg.max_deviation).abs() < 1e-3, "{what}");
    // Reaches are kept as f32: to a few millimetres.
    let slack = 1e-3 + 1e-6 * reach;
    assert!(
        far <= msg.max_hole_reach_m + slack,
        "{what}: {far} vs {}",
        msg.max_hole_reach_m
    );
    assert!(msg.max_hole_reach_m <= reach + slack, "{what}");
    (worst, drawn_voids)
}

#[test]
fn meshes_keep_their_error_and_leave_holes_open() {
    let tmp = tempfile::tempdir().unwrap();
    let engine = engine_with(
        tmp.path(),
        &["copernicus_n34w119_crop.tif", "srtm_n44e005_voids_crop.tif"],
    );
    let voids = common::real_crop("srtm_n44e005_voids_crop.tif").world_bounds();
    let cop = common::real_crop("copernicus_n34w119_crop.tif").world_bounds();
    for (name, roi) in [("copernicus", cop), ("voids", voids)] {
        let cases = [(0.0, 0.5, 129), (5.0, 2.0, 129), (20.0, 10.0, 65)];
        for ((error, mesh_error, size), method) in
            cases.into_iter().flat_map(|c| METHODS.map(|m| (c, m)))
        {
            let (m, msg) = run(
                &engine,
                &request(
                    &roi,
                    error,
                    size,
                    mesh_error,
                    0.0,
                    pb::MeshBorder::Shared,
                    method,
                ),
            );
            let (s, what) = (size as usize, format!("{name} {method:?} at e = {error}"));
            let h = grid_heights(&engine, &roi, error, s, s);
            let (worst, drawn) = check_mesh(&what, &m, &msg, &h, mesh_error, 0.0, [1.0; 2]);
            assert_eq!(drawn, 0, "{what}: no triangle reaches a void vertex");
            let holes = h.iter().filter(|z| z.is_nan()).count();
            let full = 2 * (size as usize - 1).pow(2);
            println!(
                "{name} {method:?} e = {error} m, mesh within {mesh_error} m, {size}²: {} vertices, {} triangles ({:.1}% of the grid's), max deviation {worst:.3} m, {holes} void vertices, {} patches",
                m.grid.len(),
                m.triangles.len(),
                100.0 * m.triangles.len() as f64 / full as f64,
                msg.patches
            );
            if name == "voids" {
                assert!(holes > 0, "the voids crop has voids");
            }
        }
    }
}

#[test]
fn meshes_of_any_size_and_holes_drawn_within_a_reach() {
    let tmp = tempfile::tempdir().unwrap();
    let engine = engine_with(tmp.path(), &["srtm_n44e005_voids_crop.tif"]);
    let roi = common::real_crop("srtm_n44e005_voids_crop.tif").world_bounds();
    let lat = (roi.min[1] + roi.max[1]) / 2.0;
    let scale = patchwork_core::index::query::Metric::geographic(lat).scale;
    let (error, mesh_error) = (0.0, 5.0);
    for [cols, rows] in [[129u32, 129], [100, 61], [2, 2], [3, 130]] {
        let (c, r) = (cols as usize, rows as usize);
        let h = grid_heights(&engine, &roi, error, c, r);
        let cell = [
            roi.width() / (c - 1) as f64 * scale[0],
            roi.height() / (r - 1) as f64 * scale[1],
        ];
        let holes = h.iter().filter(|z| z.is_nan()).count();
        let mut counts = Vec::new();
        for method in METHODS {
            // Reaches of none, one, three and eight cells.
            for cells in [0.0, 1.0, 3.0, 8.0] {
                let reach = cells * cell[0].max(cell[1]);
                let req = pb::MeshRequest {
                    hole_reach_m: reach,
                    ..shared(&roi, error, [cols, rows], mesh_error, method)
                };
                let (m, msg) = run(&engine, &req);
                assert_eq!((m.cols, m.rows), (c, r));
                let what = format!("{cols} × {rows} {method:?}, reach {reach:.0} m");
                let (worst, drawn) = check_mesh(&what, &m, &msg, &h, mesh_error, reach, cell);
                if cells == 0.0 {
                    assert_eq!(drawn, 0, "{what}: exact holes are open");
                }
                counts.push(format!(
                    "{} {:.0} m: {} triangles, {drawn} voids drawn, max deviation {worst:.2} m, max reach {:.0} m",
                    method.as_str_name(),
                    reach,
                    m.triangles.len(),
                    msg.max_hole_reach_m
                ));
            }
        }
        println!(
            "{cols} × {rows}, {holes} void vertices:\n  {}",
            counts.join("\n  ")
        );
    }
}

/// Which grid coordinate runs along a side of [`edges`]: the row on the west and east sides,
/// the column on the south and north ones.
fn axis_along(side: usize) -> usize {
    usize::from(side.is_multiple_of(2))
}

/// One polyline of a tile's border: the heights of its edge vertices, by grid position along
/// the side, linearly interpolated at every grid position.
fn along(m: &Mesh, side: usize) -> Vec<f64> {
    let e = &edges(m)[side];
    let pos = |v: u32| m.grid[v as usize][axis_along(side)];
    let n = if axis_along(side) == 1 {
        m.rows
    } else {
        m.cols
    };
    let mut out = vec![f64::NAN; n];
    for w in e.windows(2) {
        let (a, b) = (pos(w[0]), pos(w[1]));
        let (za, zb) = (
            m.heights[w[0] as usize] as f64,
            m.heights[w[1] as usize] as f64,
        );
        for k in a..=b {
            let f = (k - a) as f64 / (b - a).max(1) as f64;
            out[k as usize] = za + (zb - za) * f;
        }
    }
    out
}

/// Tile (i, j), row j counted from the north, of an n × n grid of tiles inside the bounds `b`,
/// with a tenth of a tile's margin at the south-west.
fn grid_tile(b: &Aabb, n: usize, i: usize, j: usize) -> Aabb {
    let side = n as f64 + 0.2;
    let (w, h) = (b.width() / side, b.height() / side);
    let (x0, y0) = (b.min[0] + 0.1 * w, b.min[1] + 0.1 * h);
    Aabb::new(
        x0 + i as f64 * w,
        y0 + (n - 1 - j) as f64 * h,
        x0 + (i + 1) as f64 * w,
        y0 + (n - j) as f64 * h,
    )
}

#[test]
fn adjacent_tiles_of_different_errors_fit_under_skirts() {
    let tmp = tempfile::tempdir().unwrap();
    let engine = engine_with(tmp.path(), &["copernicus_n34w119_crop.tif"]);
    let b = common::real_crop("copernicus_n34w119_crop.tif").world_bounds();
    // A 3 × 3 grid of tiles inside the crop, each at its own cut error and mesh error.
    let spec = |i: usize, j: usize| {
        let k = i + 3 * j;
        ([0.0, 5.0, 20.0, 2.0, 50.0][k % 5], [0.5, 2.0, 5.0][k % 3])
    };
    let bound = |i: usize, j: usize| {
        let (e, m) = spec(i, j);
        e + m
    };
    // Deep enough for any two neighbours: each is within e + m of the survey at its vertices.
    let skirt = 2.0 * (0..9).map(|k| bound(k % 3, k / 3)).fold(0.0, f64::max);
    let size = 65u32;
    let tiles: Vec<Vec<Mesh>> = (0..3)
        .map(|j| {
            (0..3)
                .map(|i| {
                    let roi = grid_tile(&b, 3, i, j);
                    let (e, m) = spec(i, j);
                    // Neighbours of both methods, so that they are seen to fit each other.
                    let method = METHODS[(i + j) % 2];
                    run(
                        &engine,
                        &request(&roi, e, size, m, skirt, pb::MeshBorder::Adaptive, method),
                    )
                    .0
                })
                .collect()
        })
        .collect();
    let (mut pairs, mut worst_gap, mut shared) = (0, 0.0f64, 0usize);
    for j in 0..3 {
        for i in 0..3 {
            // East neighbour: this tile's east side against its west side; south neighbour:
            // this tile's south side against its north side.
            let mut check = |a: &Mesh, sa: usize, b: &Mesh, sb: usize, pair: (usize, usize)| {
                let (pa, pb) = (along(a, sa), along(b, sb));
                let limit = bound(i, j) + bound(pair.0, pair.1);
                for (za, zb) in pa.iter().zip(&pb) {
                    assert!(
                        !za.is_nan() && !zb.is_nan(),
                        "a border without edge vertices"
                    );
                    let gap = (za - zb).abs();
                    worst_gap = worst_gap.max(gap);
                    // The surfaces meet within what both errors allow, and the skirt under
                    // the higher one reaches the lower.
                    assert!(
                        gap <= limit + 1e-3,
                        "a {gap} m step where {limit} m is allowed"
                    );
                    assert!(
                        gap <= skirt,
                        "a {gap} m crack deeper than the {skirt} m skirts"
                    );
                }
                // Vertices both tiles have on the shared side are at one position.
                let ea: std::collections::HashSet<u32> = edges(a)[sa]
                    .iter()
                    .map(|&v| a.grid[v as usize][axis_along(sa)])
                    .collect();
                let eb: std::collections::HashSet<u32> = edges(b)[sb]
                    .iter()
                    .map(|&v| b.grid[v as usize][axis_along(sb)])
                    .collect();
                shared += ea.intersection(&eb).count();
                pairs += 1;
            };
            if i + 1 < 3 {
                check(&tiles[j][i], 2, &tiles[j][i + 1], 0, (i + 1, j));
            }
            if j + 1 < 3 {
                check(&tiles[j][i], 1, &tiles[j + 1][i], 3, (i, j + 1));
            }
        }
    }
    // Every tile hangs a skirt from each border edge, skirt_m below it.
    for m in tiles.iter().flatten() {
        let border: usize = edges(m).iter().map(|e| e.len() - 1).sum();
        assert_eq!(m.triangles.len() - m.skirt_triangles, 2 * border);
    }
    assert_eq!(pairs, 12);
    println!(
        "12 shared sides: largest step between neighbours {worst_gap:.2} m, under skirts {skirt:.1} m deep; {shared} border positions where both have a vertex"
    );
}

#[test]
fn independent_decoders_read_the_encodings() {
    let tmp = tempfile::tempdir().unwrap();
    let engine = engine_with(tmp.path(), &["copernicus_n34w119_crop.tif"]);
    let b = common::real_crop("copernicus_n34w119_crop.tif").world_bounds();
    // A grid that is not square, nor 2ⁿ + 1 rows.
    let req = pb::MeshRequest {
        rows: 97,
        ..request(
            &b,
            5.0,
            129,
            2.0,
            30.0,
            pb::MeshBorder::Adaptive,
            pb::MeshMethod::Rtin,
        )
    };
    let (m, msg) = run(&engine, &req);
    assert_eq!((m.cols, m.rows), (129, 97));
    let (mesh, roi) = convert::mesh_of(&msg).unwrap();
    assert_eq!(mesh, m);
    let out = tmp.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(
        out.join("tile.terrain"),
        encode::quantized_mesh(
            &mesh,
            &roi,
            &encode::Extensions {
                normals: true,
                ..Default::default()
            },
        ),
    )
    .unwrap();
    // The store is geographic: glTF in metres about the tile's centre; and the same mesh as
    // if its CRS were projected, placed by the node's translation.
    std::fs::write(out.join("tile.glb"), encode::glb(&mesh, &roi, true)).unwrap();
    std::fs::write(out.join("planar.glb"), encode::glb(&mesh, &roi, false)).unwrap();
    std::fs::write(out.join("tile.obj"), encode::obj(&mesh, &roi)).unwrap();
    let surface = &mesh.heights[..mesh.skirt_vertices];
    let range = |v: &[f32]| {
        v.iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &z| {
                (a.min(z), b.max(z))
            })
    };
    let expected = serde_json::json!({
        "roi": [roi.min[0], roi.min[1], roi.max[0], roi.max[1]],
        "vertices": mesh.grid.len(),
        "triangles": mesh.triangles.len(),
        "surface_vertices": mesh.skirt_vertices,
        "surface_triangles": mesh.skirt_triangles,
        "edges": edges(&mesh).iter().map(|e| e.len()).collect::<Vec<_>>(),
        "height_range": <[f32; 2]>::from(range(surface)),
        "all_height_range": <[f32; 2]>::from(range(&mesh.heights)),
    });
    std::fs::write(out.join("expected.json"), expected.to_string()).unwrap();
    let python = common::python::python();
    let run = Command::new(&python)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .arg("tests/python/meshes.py")
        .arg(&out)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&run.stderr)
    );
    println!("{}", stdout.trim_end());
}

#[test]
fn tiles_of_one_error_with_shared_borders_fit_without_skirts() {
    let tmp = tempfile::tempdir().unwrap();
    let engine = engine_with(tmp.path(), &["copernicus_n34w119_crop.tif"]);
    let b = common::real_crop("copernicus_n34w119_crop.tif").world_bounds();
    // Square 2ⁿ + 1 grids, and ones that are neither (padded inside the mesher).
    let cases = [
        (0.0, 1.0, [65, 65]),
        (5.0, 2.0, [65, 65]),
        (20.0, 10.0, [65, 65]),
        (0.0, 1.0, [50, 37]),
        (5.0, 2.0, [100, 71]),
    ];
    for (error, mesh_error, [cols, rows]) in cases {
        let tile = |i: usize, j: usize| {
            let roi = grid_tile(&b, 2, i, j);
            let req = shared(&roi, error, [cols, rows], mesh_error, METHODS[(i + j) % 2]);
            run(&engine, &req).0
        };
        let t = [[tile(0, 0), tile(1, 0)], [tile(0, 1), tile(1, 1)]];
        let mut worst = 0.0f64;
        for (a, sa, b, sb) in [
            (&t[0][0], 2, &t[0][1], 0),
            (&t[1][0], 2, &t[1][1], 0),
            (&t[0][0], 1, &t[1][0], 3),
            (&t[0][1], 1, &t[1][1], 3),
        ] {
            // Both sides hold every grid vertex of the shared side, at one height.
            let (ea, eb) = (&edges(a)[sa], &edges(b)[sb]);
            let along = axis_along(sa);
            let n = if along == 1 { rows } else { cols } as usize;
            assert_eq!(ea.len(), n);
            assert_eq!(eb.len(), n);
            for (&va, &vb) in ea.iter().zip(eb) {
                assert_eq!(a.grid[va as usize][along], b.grid[vb as usize][along]);
                let gap = (a.heights[va as usize] - b.heights[vb as usize]).abs() as f64;
                worst = worst.max(gap);
            }
        }
        // No step along a shared side: the same cut gives a point the same height in every
        // tile that holds it.
        assert!(worst <= 1e-3, "e = {error}: a {worst} m step between tiles");
        let tris: usize = t.iter().flatten().map(|m| m.triangles.len()).sum();
        println!("e = {error} m, mesh within {mesh_error} m: 4 tiles of {cols} × {rows} (RTIN and quadtree side by side), {tris} triangles, largest step at shared sides {worst:.1e} m");
    }
}
