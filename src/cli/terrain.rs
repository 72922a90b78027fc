//! The Terrain service's commands: patches of a cut, tiles, heights at points, and meshes.

use super::client::{call, collect, Client};
use super::json::{PatchJson, QueryJson, SampleJson, SourceJson};
use super::{achieved, numbers, rect, CutArgs, Fail, MeshArgs, QueryArgs, SampleArgs, TileArgs};
use patchwork::engine::{Engine, SampleRequest, TileRequest};
use patchwork::serve::door::MeshAsk;
use patchwork::serve::proto as pb;
use patchwork::serve::{api, convert};
use patchwork_core::mesh::encode;
use std::path::Path;

pub async fn query(args: QueryArgs) -> Result<(), Fail> {
    let QueryArgs { cut, json, target } = args;
    let mut c = Client::connect(&target).await?;
    let q = match (view_of(&cut)?, &cut.roi) {
        (Some(v), None) => pb::PatchQuery {
            cut: Some(pb::patch_query::Cut::View(v)),
            batch_size: 0,
            crs: cut.crs.clone().unwrap_or_default(),
        },
        (None, Some(roi)) => pb::PatchQuery {
            cut: Some(pb::patch_query::Cut::Uniform(pb::UniformCut {
                roi: Some(rect(roi)?),
                error: cut.error.ok_or("--roi needs --error")?,
            })),
            batch_size: 0,
            crs: cut.crs.clone().unwrap_or_default(),
        },
        _ => return Err("give either --roi with --error, or --eye and --look".into()),
    };
    let patches: Vec<pb::Patch> = match &mut c {
        Client::Remote { terrain, .. } => collect(terrain.query_patches(q).await)
            .await?
            .into_iter()
            .flat_map(|b| b.patches)
            .collect(),
        Client::Local(e) => api::query_patches(e, &q)
            .map_err(|e| -> Fail { e.to_string().into() })?
            .into_iter()
            .flat_map(|b| b.patches)
            .collect(),
    };
    if json {
        let v = QueryJson {
            patches: patches.iter().map(PatchJson::of).collect(),
        };
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for p in &patches {
            let b = p.bounds.unwrap_or_default();
            println!(
                "{:016x}  survey {:016x}  level {}  error {:.3}..{:.3} m  [{}, {}, {}, {}]",
                p.id, p.survey, p.level, p.error, p.max_error, b.xmin, b.ymin, b.xmax, b.ymax
            );
        }
        println!("{} patches", patches.len());
    }
    Ok(())
}

pub async fn tile(args: TileArgs) -> Result<(), Fail> {
    let TileArgs {
        roi,
        size,
        error,
        backend,
        crs,
        out,
        heights,
        target,
    } = args;
    let mut c = Client::connect(&target).await?;
    let roi = rect(&roi)?;
    let (w, h) = size
        .split_once(['x', 'X'])
        .and_then(|(a, b)| Some((a.parse::<u32>().ok()?, b.parse::<u32>().ok()?)))
        .ok_or_else(|| format!("--size: expected WxH, e.g. 512x512, got {size:?}"))?;
    let backend = pb::Backend::from(backend);
    c.open_gpu_for(backend).await?;
    let req = pb::TileRequest {
        cut: Some(pb::tile_request::Cut::Uniform(pb::UniformCut {
            roi: Some(roi),
            error,
        })),
        width: w,
        height: h,
        backend: backend as i32,
        crs: crs.unwrap_or_default(),
        heights,
    };
    let bands = match &mut c {
        Client::Remote { terrain, .. } => collect(terrain.tile_bands(req).await).await?,
        Client::Local(engine) => {
            let engine = engine.clone();
            tokio::task::spawn_blocking(move || {
                let mut bands = Vec::new();
                let req = TileRequest::try_from(&req)?;
                api::tile_bands(&engine, &req, &Default::default(), &mut |b| {
                    bands.push(b);
                    true
                })
                .map(|()| bands)
            })
            .await??
        }
    };
    let t = assemble(bands)?;
    write_tile(&out, &t, &roi)?;
    let valid = t.heights.iter().filter(|z| !z.is_nan()).count();
    println!(
        "wrote {} ({}×{}, {} valid samples, {} patches, {}, {})",
        out.display(),
        t.width,
        t.height,
        valid,
        t.patches,
        achieved(error, t.max_error, t.shortfall.as_ref(), "tile"),
        t.backend
    );
    Ok(())
}

pub async fn sample(args: SampleArgs) -> Result<(), Fail> {
    let SampleArgs {
        points,
        line,
        count,
        error,
        crs,
        json,
        heights,
        sources,
        target,
    } = args;
    let pts: Vec<[f64; 2]> = match (&points, &line) {
        (Some(p), None) => {
            let v: Vec<f64> = p
                .split(',')
                .map(|t| t.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|_| format!("--points: expected X,Y pairs, got {p:?}"))?;
            if v.is_empty() || !v.len().is_multiple_of(2) {
                return Err(format!("--points: expected X,Y pairs, got {p:?}").into());
            }
            v.chunks(2).map(|c| [c[0], c[1]]).collect()
        }
        (None, Some(l)) => {
            let [x0, y0, x1, y1] = numbers::<4>(l, "--line")?;
            let n = count.max(2);
            (0..n)
                .map(|k| {
                    let t = k as f64 / (n - 1) as f64;
                    [x0 + t * (x1 - x0), y0 + t * (y1 - y0)]
                })
                .collect()
        }
        _ => return Err("give either --points or --line".into()),
    };
    let mut c = Client::connect(&target).await?;
    let req = pb::SampleRequest {
        points: pts.iter().map(|p| pb::Point { x: p[0], y: p[1] }).collect(),
        error,
        crs: crs.unwrap_or_default(),
        heights,
        sources,
    };
    let local = req.clone();
    let r = call!(&mut c, terrain.sample_heights(req), move |e: &Engine| {
        api::sample_heights(e, &SampleRequest::try_from(&local)?, &Default::default())
    })?;
    let height = |k: usize| (r.valid.get(k) == Some(&1)).then(|| r.heights[k]);
    if json {
        let v: Vec<SampleJson> = pts
            .iter()
            .enumerate()
            .map(|(k, p)| SampleJson {
                x: p[0],
                y: p[1],
                height: height(k),
                source: sources.then(|| r.sources.get(k).and_then(SourceJson::of)),
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for (k, p) in pts.iter().enumerate() {
            let from = match r.sources.get(k).and_then(SourceJson::of) {
                Some(_) => {
                    let s = &r.sources[k];
                    format!(
                        "  from {} ({}, level {}, cell {:.1} m, error {:.2} m)",
                        s.survey, s.file, s.level, s.cell_m, s.error_m
                    )
                }
                None => String::new(),
            };
            match height(k) {
                Some(z) => println!("{} {} {z}{from}", p[0], p[1]),
                None => println!("{} {} nodata", p[0], p[1]),
            }
        }
    }
    Ok(())
}

pub async fn mesh(args: MeshArgs) -> Result<(), Fail> {
    let MeshArgs {
        roi,
        error,
        mesh_error,
        size,
        rows,
        hole_reach,
        skirt,
        border,
        method,
        backend,
        crs,
        out,
        heights,
        target,
    } = args;
    let kind = out.extension().and_then(|e| e.to_str()).unwrap_or("");
    if !["obj", "glb", "terrain"].contains(&kind) {
        return Err(format!("--out {}: write .obj, .glb or .terrain", out.display()).into());
    }
    let mut c = Client::connect(&target).await?;
    c.open_gpu_for(pb::Backend::from(backend)).await?;
    let req = pb::MeshRequest {
        cut: Some(pb::UniformCut {
            roi: Some(rect(&roi)?),
            error,
        }),
        size,
        rows: rows.unwrap_or(size),
        mesh_error,
        hole_reach_m: hole_reach,
        skirt_m: skirt,
        backend: pb::Backend::from(backend) as i32,
        border: pb::MeshBorder::from(border) as i32,
        method: pb::MeshMethod::from(method) as i32,
        crs: crs.unwrap_or_default(),
        heights,
    };
    let local = req.clone();
    let m = call!(&mut c, terrain.mesh_tile(req), move |e: &Engine| {
        api::mesh_tile(e, &MeshAsk::try_from(&local)?, &Default::default())
    })?;
    let (mesh, tile) = convert::mesh_of(&m)?;
    let bytes = match kind {
        "obj" => encode::obj(&mesh, &tile).into_bytes(),
        "glb" => {
            let lonlat = tile_crs(&m.crs_key)?.is_some_and(|c| c.is_geographic());
            encode::glb(&mesh, &tile, lonlat)
        }
        _ => {
            let crs = tile_crs(&m.crs_key)?;
            if !crs.as_ref().is_some_and(|c| c.is_geographic()) {
                return Err(format!(
                        "quantized-mesh tiles are in longitude and latitude; this mesh is in {} (ask with --crs EPSG:4326)",
                        crs.map_or("no CRS".into(), |c| c.label())
                    )
                    .into());
            }
            encode::quantized_mesh(
                &mesh,
                &tile,
                &encode::Extensions {
                    normals: true,
                    ..Default::default()
                },
            )
        }
    };
    std::fs::write(&out, bytes)?;
    println!(
            "wrote {} ({} vertices, {} triangles of which {} skirt; max deviation {:.3} m from the resampled heights, surface up to {:.1} m over voids; {} patches, {}, {})",
            out.display(),
            mesh.grid.len(),
            mesh.triangles.len(),
            mesh.triangles.len() - mesh.skirt_triangles,
            mesh.max_deviation,
            mesh.max_reach,
            m.patches,
            achieved(error, m.max_error, m.shortfall.as_ref(), "mesh"),
            m.backend
        );
    Ok(())
}

fn view_of(c: &CutArgs) -> Result<Option<pb::ViewCut>, Fail> {
    match (&c.eye, &c.look) {
        (Some(e), Some(l)) => {
            let [ex, ey, ez] = numbers::<3>(e, "--eye")?;
            let [lx, ly, lz] = numbers::<3>(l, "--look")?;
            Ok(Some(pb::ViewCut {
                eye_x: ex,
                eye_y: ey,
                eye_z: ez,
                look_x: lx,
                look_y: ly,
                look_z: lz,
                fov_deg: c.fov,
                viewport_px: c.viewport,
                pixel_error: c.pixel_error,
                ..Default::default()
            }))
        }
        (None, None) => Ok(None),
        _ => Err("a view needs both --eye and --look".into()),
    }
}

/// A tile put back together from its bands, which must cover its rows in order.
fn assemble(bands: Vec<pb::TileBand>) -> Result<pb::Tile, Fail> {
    let Some(first) = bands.first() else {
        return Err("the daemon sent no tile".into());
    };
    let (width, height) = (first.width as usize, first.height as usize);
    let mut t = pb::Tile {
        width: first.width,
        height: first.height,
        patches: first.patches,
        backend: first.backend.clone(),
        crs: first.crs,
        crs_key: first.crs_key.clone(),
        max_error: first.max_error,
        shortfall: first.shortfall,
        heights: Vec::with_capacity(width * height),
        valid: Vec::new(),
        vertical_crs: first.vertical_crs.clone(),
        frame_error_m: 0.0,
    };
    for b in &bands {
        let row = t.heights.len() / width.max(1);
        if b.row as usize != row || b.heights.len() != 4 * width * b.rows as usize {
            return Err(format!(
                "band at row {} of {} rows does not follow row {row}",
                b.row, b.rows
            )
            .into());
        }
        t.heights.extend(
            b.heights
                .chunks_exact(4)
                .map(|q| f32::from_le_bytes([q[0], q[1], q[2], q[3]])),
        );
    }
    if t.heights.len() != width * height {
        return Err(format!(
            "the bands hold {} of the tile's {} heights",
            t.heights.len(),
            width * height
        )
        .into());
    }
    Ok(t)
}

/// The CRS a reply names by its key; None for an empty key.
pub fn tile_crs(key: &str) -> Result<Option<patchwork_core::crs::Crs>, Fail> {
    if key.is_empty() {
        return Ok(None);
    }
    Ok(Some(patchwork_core::crs::Crs::parse(key)?))
}

fn write_tile(out: &Path, t: &pb::Tile, roi: &pb::Rect) -> Result<(), Fail> {
    match out.extension().and_then(|e| e.to_str()) {
        Some("tif") | Some("tiff") => {
            let gt = [
                roi.xmin,
                (roi.xmax - roi.xmin) / t.width as f64,
                0.0,
                roi.ymax,
                0.0,
                -(roi.ymax - roi.ymin) / t.height as f64,
            ];
            patchwork_read::write_tiff::write_geotiff_f32(
                out,
                t.width as usize,
                t.height as usize,
                &t.heights,
                gt,
                tile_crs(&t.crs_key)?.as_ref(),
                Some(-9999.0),
            )?;
        }
        Some("npy") => {
            patchwork_read::write_npy(out, t.height as usize, t.width as usize, &t.heights)?
        }
        _ => return Err(format!("--out {}: use a .tif or .npy name", out.display()).into()),
    }
    Ok(())
}
