//! The bench's charts, drawn once for PNG and once for SVG from the same code, and the map in
//! the style of the paper's Fig. 5.

use super::{Report, ERRORS};
use patchwork_core::geom::Aabb;
use patchwork_core::resample::SampleGrid;
use patchwork_core::terrain::Terrain;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

use crate::Fail;

fn fonts() {
    static DONE: OnceLock<()> = OnceLock::new();
    DONE.get_or_init(|| {
        // Embedded so that charts render the same on any machine, fonts installed or not.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("font/DejaVuSans.ttf"),
        );
    });
}

struct Chart<'a> {
    title: &'a str,
    x: &'a str,
    y: &'a str,
    series: Vec<(String, Vec<(f64, f64)>)>,
    log_y: bool,
    /// Draw y = x: the bound a measured error must stay under.
    diagonal: bool,
    /// Points only, no lines between them: a scatter.
    scatter: bool,
}

const COLORS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

fn draw_chart<DB: DrawingBackend>(root: DrawingArea<DB, Shift>, c: &Chart) -> Result<(), String> {
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| format!("{x:?}");
    root.fill(&WHITE).map_err(e)?;
    let pts = c.series.iter().flat_map(|(_, p)| p.iter());
    let xmax = pts.clone().map(|p| p.0).fold(1e-9, f64::max) * 1.05;
    let (ymin, ymax) = pts
        .filter(|p| !c.log_y || p.1 > 0.0)
        .fold((f64::INFINITY, 0.0f64), |(a, b), p| {
            (a.min(p.1), b.max(p.1))
        });
    let ymax = if c.diagonal { ymax.max(xmax) } else { ymax } * 1.1 + 1e-9;
    let mut b = ChartBuilder::on(&root);
    b.caption(c.title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70);
    let lines = |series: &[(String, Vec<(f64, f64)>)]| series.to_vec();
    if c.log_y {
        let lo = if ymin.is_finite() { ymin / 1.5 } else { 1e-3 };
        let mut ch = b
            .build_cartesian_2d(0.0..xmax, (lo..ymax).log_scale())
            .map_err(e)?;
        ch.configure_mesh()
            .x_desc(c.x)
            .y_desc(c.y)
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(e)?;
        for (i, (name, p)) in lines(&c.series).into_iter().enumerate() {
            let col = COLORS[i % COLORS.len()];
            let p: Vec<_> = p.into_iter().filter(|q| q.1 > 0.0).collect();
            ch.draw_series(LineSeries::new(p.clone(), col.stroke_width(2)))
                .map_err(e)?
                .label(name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], col.stroke_width(2))
                });
            ch.draw_series(p.into_iter().map(|q| Circle::new(q, 3, col.filled())))
                .map_err(e)?;
        }
        ch.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(e)?;
    } else {
        let mut ch = b.build_cartesian_2d(0.0..xmax, 0.0..ymax).map_err(e)?;
        ch.configure_mesh()
            .x_desc(c.x)
            .y_desc(c.y)
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(e)?;
        if c.diagonal {
            ch.draw_series(LineSeries::new(
                vec![(0.0, 0.0), (xmax, xmax)],
                BLACK.stroke_width(1),
            ))
            .map_err(e)?
            .label("bound: y = e")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
        }
        for (i, (name, p)) in lines(&c.series).into_iter().enumerate() {
            let col = COLORS[i % COLORS.len()];
            if c.scatter {
                ch.draw_series(
                    p.into_iter()
                        .map(|q| Circle::new(q, 2, col.mix(0.6).filled())),
                )
                .map_err(e)?
                .label(name)
                .legend(move |(x, y)| Circle::new((x + 10, y), 4, col.filled()));
                continue;
            }
            ch.draw_series(LineSeries::new(p.clone(), col.stroke_width(2)))
                .map_err(e)?
                .label(name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], col.stroke_width(2))
                });
            ch.draw_series(p.into_iter().map(|q| Circle::new(q, 3, col.filled())))
                .map_err(e)?;
        }
        ch.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(e)?;
    }
    root.present().map_err(e)?;
    Ok(())
}

fn both(out: &Path, name: &str, c: &Chart) -> Result<(), Fail> {
    let size = (820, 520);
    draw_chart(
        BitMapBackend::new(&out.join(format!("{name}.png")), size).into_drawing_area(),
        c,
    )?;
    draw_chart(
        SVGBackend::new(&out.join(format!("{name}.svg")), size).into_drawing_area(),
        c,
    )?;
    Ok(())
}

/// Draws every chart of `r` under `out`, and the patch map of `t` over `map_roi`.
pub fn draw(out: &Path, r: &Report, t: &Terrain, map_roi: &Aabb, smoke: bool) -> Result<(), Fail> {
    fonts();
    let by_roi = |f: &dyn Fn(&super::UniformRow) -> f64| -> Vec<(String, Vec<(f64, f64)>)> {
        ["small", "medium", "large"]
            .iter()
            .map(|roi| {
                let p = r
                    .uniform
                    .iter()
                    .filter(|u| u.roi == *roi)
                    .map(|u| (u.error, f(u)))
                    .collect();
                (format!("{roi} ROI"), p)
            })
            .collect()
    };
    let mut time = by_roi(&|u| u.query_ms);
    for s in &mut time {
        s.0 = format!("query, {}", s.0);
    }
    let mut resample = by_roi(&|u| u.resample_ms);
    for s in &mut resample {
        s.0 = format!("resample {}², {}", r.uniform[0].tile, s.0);
    }
    time.extend(resample);
    both(
        out,
        "time_vs_error",
        &Chart {
            title: "Time against requested error",
            x: "requested error e (m)",
            y: "median time (ms)",
            series: time,
            log_y: true,
            diagonal: false,
            scatter: false,
        },
    )?;
    both(
        out,
        "patches_vs_error",
        &Chart {
            title: "Patches against requested error",
            x: "requested error e (m)",
            y: "patches returned",
            series: by_roi(&|u| u.patches as f64),
            log_y: true,
            diagonal: false,
            scatter: false,
        },
    )?;
    let mut acc = Vec::new();
    for (name, f) in [
        (
            "max",
            (|u: &super::UniformRow| u.max_err) as fn(&super::UniformRow) -> f64,
        ),
        ("RMS", |u: &super::UniformRow| u.rms_err),
    ] {
        for (roi, p) in by_roi(&f) {
            acc.push((format!("{name}, {roi}"), p));
        }
    }
    both(
        out,
        "error_vs_requested",
        &Chart {
            title: "Measured error of the resampled tiles",
            x: "requested error e (m)",
            y: "measured error (m)",
            series: acc,
            log_y: false,
            diagonal: true,
            scatter: false,
        },
    )?;
    // Where methods break: the largest deviation each case measured with bicubic patches,
    // the worst with bilinear ones (whose bound is y = e), and the largest bound the bicubic
    // cuts had to keep; each the worst over the filters at each e.
    let worst = |keep: &dyn Fn(&super::stability::StabilityRow) -> bool,
                 f: fn(&super::stability::StabilityRow) -> f64|
     -> Vec<(f64, f64)> {
        super::stability::ERRORS
            .iter()
            .map(|&e| {
                let v = r
                    .stability
                    .iter()
                    .filter(|s| s.error == e && keep(s))
                    .map(f)
                    .fold(0.0f64, f64::max);
                (e, v)
            })
            .collect()
    };
    use patchwork_core::model::patch::PatchKind;
    let mut stab = vec![(
        "bilinear, every case".to_string(),
        worst(&|s| s.recipe.patches == PatchKind::Bilinear, |s| s.measured),
    )];
    for case in ["cliff", "spikes", "voids", "rotated"] {
        stab.push((
            format!("bicubic, {case}"),
            worst(
                &|s| s.recipe.patches == PatchKind::Bicubic && s.case == case,
                |s| s.measured,
            ),
        ));
    }
    stab.push((
        "bicubic, the bound kept".to_string(),
        worst(&|s| s.recipe.patches == PatchKind::Bicubic, |s| s.bound),
    ));
    both(
        out,
        "stability",
        &Chart {
            title: "Largest deviation at cliffs, spikes, voids and rotations",
            x: "requested error e (m)",
            y: "metres",
            series: stab,
            log_y: true,
            diagonal: true,
            scatter: false,
        },
    )?;
    let view_t = vec![(
        "median query time (ms)".to_string(),
        r.view.iter().map(|v| (v.pixel_error, v.query_ms)).collect(),
    )];
    both(
        out,
        "view_time",
        &Chart {
            title: "View-dependent queries along a flight",
            x: "screen error (pixels)",
            y: "ms",
            series: view_t,
            log_y: false,
            diagonal: false,
            scatter: false,
        },
    )?;
    let view_p = vec![(
        "patches per view".to_string(),
        r.view.iter().map(|v| (v.pixel_error, v.patches)).collect(),
    )];
    both(
        out,
        "view_patches",
        &Chart {
            title: "Patches per view along a flight",
            x: "screen error (pixels)",
            y: "patches",
            series: view_p,
            log_y: false,
            diagonal: false,
            scatter: false,
        },
    )?;
    let mut flight = Vec::new();
    for (speed, _) in super::flight::SPEEDS {
        let rows = r.flight.iter().filter(|f| f.speed == speed);
        let kb = |b: usize| b as f64 / 1e3;
        flight.push((
            format!("{speed}: delta"),
            rows.clone()
                .map(|f| (f.frame as f64, kb(f.delta_bytes)))
                .collect(),
        ));
        flight.push((
            format!("{speed}: whole cut"),
            rows.map(|f| (f.frame as f64, kb(f.full_bytes))).collect(),
        ));
    }
    both(
        out,
        "view_session",
        &Chart {
            title: "Bytes per frame of a view session, delta against whole cut",
            x: "frame",
            y: "kB (log)",
            series: flight,
            log_y: true,
            diagonal: false,
            scatter: false,
        },
    )?;
    let sc = &r.scenes;
    let mixed = |scene: &str, f: fn(&super::meet::MixedRow) -> f64| -> Vec<(f64, f64)> {
        sc.mixed
            .iter()
            .filter(|m| m.scene == scene)
            .map(|m| (m.error, f(m)))
            .collect()
    };
    both(
        out,
        "mixed_error_vs_requested",
        &Chart {
            title: "Error against the finer survey where surveys overlap",
            x: "requested error e (m)",
            y: "measured error (m)",
            series: vec![
                (
                    "30 m + 90 m copy (ε estimated): max".into(),
                    mixed("copies", |m| m.max_err),
                ),
                (
                    "30 m + 90 m copy: RMS".into(),
                    mixed("copies", |m| m.rms_err),
                ),
                (
                    "ε 2 m inside ε 20 m: max over the ε 2 m survey".into(),
                    mixed("nested", |m| m.max_err),
                ),
                (
                    "ε 2 m inside ε 20 m: RMS".into(),
                    mixed("nested", |m| m.rms_err),
                ),
            ],
            log_y: false,
            diagonal: true,
            scatter: false,
        },
    )?;
    let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for c in &sc.copies {
        series.push((
            format!(
                "copy by {}: survey ε {:.1} m, measured {:.1} m",
                c.factor, c.estimated, c.measured_max
            ),
            sc.estimator
                .iter()
                .filter(|e| e.factor == c.factor)
                .map(|e| (e.measured, e.estimated))
                .collect(),
        ));
    }
    both(
        out,
        "estimator",
        &Chart {
            title: "Estimated ε against measured error, per kernel of decimated copies",
            x: "largest deviation from the original in the kernel (m)",
            y: "estimated ε (m)",
            series,
            log_y: false,
            diagonal: true,
            scatter: true,
        },
    )?;
    map(out, t, map_roi, if smoke { 96 } else { 420 })?;
    let _ = ERRORS;
    Ok(())
}

/// Hillshade coloured by the level of the patch that represents each point, at three errors,
/// as in the paper's Fig. 5: red for the finest patches, blue for the largest.
fn map(out: &Path, t: &Terrain, roi: &Aabb, n: usize) -> Result<(), Fail> {
    let errors = [5.0, 20.0, 50.0];
    let path = out.join("patch_map.png");
    let root =
        BitMapBackend::new(&path, ((n * 3 + 40) as u32, (n + 50) as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| format!("{e:?}"))?;
    let grid = SampleGrid::uniform(roi, n, n);
    let metric = match t.surveys().next().and_then(|s| s.crs.clone()) {
        Some(c) if c.is_geographic() => {
            patchwork_core::index::query::Metric::geographic((roi.min[1] + roi.max[1]) / 2.0)
        }
        _ => patchwork_core::index::query::Metric::PROJECTED,
    };
    let dx = roi.width() / n as f64 * metric.scale[0];
    let dy = roi.height() / n as f64 * metric.scale[1];
    for (k, &e) in errors.iter().enumerate() {
        let ps = t.uniform(roi, e);
        let tile = t.resample(ps.clone(), &grid);
        let levels: Vec<u8> = grid
            .points()
            .map(|p| {
                ps.iter()
                    .filter(|x| x.kernel.contains_point(p))
                    .map(|x| x.level)
                    .max()
                    .unwrap_or(0)
            })
            .collect();
        let h = |i: usize, j: usize| tile.heights[j.min(n - 1) * n + i.min(n - 1)] as f64;
        let x0 = 10 + k * (n + 10);
        root.draw(&Text::new(
            format!("e = {e} m: {} patches", ps.len()),
            (x0 as i32, 8),
            ("sans-serif", 15),
        ))
        .map_err(|e| format!("{e:?}"))?;
        let area = root.margin(30, 20, x0 as i32, 0);
        for j in 0..n {
            for i in 0..n {
                let z = h(i, j);
                if z.is_nan() {
                    continue;
                }
                let gx = (h(i + 1, j) - h(i.saturating_sub(1), j)) / (2.0 * dx);
                let gy = (h(i, j.saturating_sub(1)) - h(i, j + 1)) / (2.0 * dy);
                let (gx, gy) = (
                    if gx.is_nan() { 0.0 } else { gx },
                    if gy.is_nan() { 0.0 } else { gy },
                );
                // Light from the north-west, 45° up.
                let shade =
                    ((1.0 + gx * 0.5 - gy * 0.5) / (1.0 + gx * gx + gy * gy).sqrt() / 1.2247)
                        .clamp(0.0, 1.0);
                let base = level_colour(levels[j * n + i]);
                let s = 0.35 + 0.65 * shade;
                let col = RGBColor(
                    (base.0 as f64 * s) as u8,
                    (base.1 as f64 * s) as u8,
                    (base.2 as f64 * s) as u8,
                );
                area.draw_pixel((i as i32, j as i32), &col)
                    .map_err(|e| format!("{e:?}"))?;
            }
        }
    }
    // The legend: one swatch per level, the same colours in every panel.
    for lv in 0..=MAX_LEVEL {
        let x = 10 + lv as i32 * 110;
        let y = (n + 32) as i32;
        root.draw(&Rectangle::new(
            [(x, y), (x + 14, y + 14)],
            level_colour(lv).filled(),
        ))
        .map_err(|e| format!("{e:?}"))?;
        let side = 28u32 << lv;
        root.draw(&Text::new(
            format!("level {lv} ({side} cells)"),
            (x + 18, y),
            ("sans-serif", 12),
        ))
        .map_err(|e| format!("{e:?}"))?;
    }
    root.present().map_err(|e| format!("{e:?}"))?;
    Ok(())
}

const MAX_LEVEL: u8 = 7;

/// Red for the finest patches through yellow to blue for the largest.
fn level_colour(level: u8) -> RGBColor {
    const STOPS: [(u8, u8, u8); 5] = [
        (215, 48, 39),
        (252, 141, 89),
        (254, 224, 144),
        (145, 191, 219),
        (69, 117, 180),
    ];
    let f = (level.min(MAX_LEVEL) as f64 / MAX_LEVEL as f64) * (STOPS.len() - 1) as f64;
    let (i, t) = (
        (f.floor() as usize).min(STOPS.len() - 2),
        f - f.floor().min((STOPS.len() - 2) as f64),
    );
    let mix = |a: u8, b: u8| (a as f64 + (b as f64 - a as f64) * t) as u8;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// For every kind of copy (numbered as in `copies.csv`) of the first scene: the median ε of
/// the original and of the copy, estimated and as served, and the RMS error of the tile at
/// the larger error against the original, with claims kept as made and distrusted.
pub fn copies(out: &Path, cases: &[super::evidence::Case]) -> Result<(), Fail> {
    fonts();
    for (k, scene) in cases
        .iter()
        .map(|c| c.scene.as_str())
        .fold(Vec::<&str>::new(), |mut v, s| {
            if !v.contains(&s) {
                v.push(s);
            }
            v
        })
        .into_iter()
        .enumerate()
    {
        let of: Vec<&super::evidence::Case> = cases.iter().filter(|c| c.scene == scene).collect();
        let series = |f: &dyn Fn(&super::evidence::Case) -> f64| -> Vec<(f64, f64)> {
            of.iter()
                .enumerate()
                .map(|(i, c)| ((i + 1) as f64, f(c)))
                .collect()
        };
        let last = |c: &super::evidence::Case| *c.tiles.last().expect("tiles");
        let title = format!("Copies of {scene}: ε and the served tile's error, before and after");
        both(
            out,
            &format!("copies_{k}"),
            &Chart {
                title: &title,
                x: "copy (1-3 blur σ 1-3, 4-6 shifts, 7-8 blur + shift (+ noise), 9 offset 30 m, 10-11 every 2nd, 3rd)",
                y: "metres",
                series: vec![
                    ("original's ε (median), estimated".into(), series(&|c| c.orig_claimed)),
                    ("copy's ε (median), estimated".into(), series(&|c| c.copy_claimed)),
                    ("copy's ε (median), as served".into(), series(&|c| c.copy_served)),
                    (
                        format!("tile at e = {} off the original, RMS: claims kept", of[0].tiles.last().map_or(0.0, |t| t.error)),
                        series(&|c| last(c).before_rms),
                    ),
                    ("the same, contradicted claims distrusted".into(), series(&|c| last(c).after_rms)),
                    ("the store without the copy".into(), series(&|c| last(c).without_rms)),
                ],
                log_y: false,
                diagonal: false,
                scatter: false,
            },
        )?;
    }
    Ok(())
}

/// Each draw of degraded copies (`draws.csv`): the share of the original's samples it still
/// serves within its own claim, draws sorted from the worst, a series a scene.
pub fn draws(out: &Path, rows: &[(String, f64)]) -> Result<(), Fail> {
    fonts();
    let mut order: Vec<usize> = (0..rows.len()).collect();
    order.sort_by(|&a, &b| rows[a].1.total_cmp(&rows[b].1));
    let mut scenes: Vec<&str> = Vec::new();
    for (s, _) in rows {
        if !scenes.contains(&s.as_str()) {
            scenes.push(s);
        }
    }
    let series = scenes
        .iter()
        .map(|scene| {
            let pts = order
                .iter()
                .enumerate()
                .filter(|(_, &k)| rows[k].0 == *scene)
                .map(|(rank, &k)| ((rank + 1) as f64, 100.0 * rows[k].1))
                .collect();
            (scene.to_string(), pts)
        })
        .collect();
    let title = format!(
        "{} draws of degraded copies: the original's samples served within its claim",
        rows.len()
    );
    both(
        out,
        "draws",
        &Chart {
            title: &title,
            x: "draw, from the worst",
            y: "% of the original's samples",
            series,
            log_y: false,
            diagonal: false,
            scatter: true,
        },
    )
}

/// Shares drawn by kind (`rows`: kind, share), draws sorted from the worst, a series a kind,
/// as `file`.svg and .png, titled by `what`.
pub fn draws_by(out: &Path, file: &str, what: &str, rows: &[(String, f64)]) -> Result<(), Fail> {
    fonts();
    let mut order: Vec<usize> = (0..rows.len()).collect();
    order.sort_by(|&a, &b| rows[a].1.total_cmp(&rows[b].1));
    let mut kinds: Vec<&str> = Vec::new();
    for (k, _) in rows {
        if !kinds.contains(&k.as_str()) {
            kinds.push(k);
        }
    }
    let series = kinds
        .iter()
        .map(|kind| {
            let pts = order
                .iter()
                .enumerate()
                .filter(|(_, &k)| rows[k].0 == *kind)
                .map(|(rank, &k)| ((rank + 1) as f64, 100.0 * rows[k].1))
                .collect();
            (kind.to_string(), pts)
        })
        .collect();
    let title = format!("{} {what}", rows.len());
    both(
        out,
        file,
        &Chart {
            title: &title,
            x: "draw, from the worst",
            y: "% of the samples",
            series,
            log_y: false,
            diagonal: false,
            scatter: true,
        },
    )
}

/// Windows underestimated and M/N_T by level, a series a survey and share.
pub fn wavelet(out: &Path, rows: &[super::wavelet::Row]) -> Result<(), Fail> {
    fonts();
    let mut keys: Vec<(String, f64)> = Vec::new();
    for r in rows {
        if !keys.iter().any(|k| k.0 == r.survey && k.1 == r.share) {
            keys.push((r.survey.clone(), r.share));
        }
    }
    let series = |y: &dyn Fn(&super::wavelet::Row) -> f64| -> Vec<(String, Vec<(f64, f64)>)> {
        keys.iter()
            .map(|(s, q)| {
                let short = s.split(['_', '.']).next().unwrap_or(s);
                (
                    format!("{short}, q = 1/{:.0}", 1.0 / q),
                    rows.iter()
                        .filter(|r| &r.survey == s && r.share == *q)
                        .map(|r| (r.level as f64, y(r)))
                        .collect(),
                )
            })
            .collect()
    };
    both(
        out,
        "wavelet_under",
        &Chart {
            title: "Haar estimate of a patch's δ: windows where it falls below δ",
            x: "mipmap level",
            y: "% of windows underestimated",
            series: series(&|r| 100.0 * r.under as f64 / r.windows.max(1) as f64),
            log_y: false,
            diagonal: false,
            scatter: false,
        },
    )?;
    both(
        out,
        "wavelet_mnt",
        &Chart {
            title: "Haar estimate of a patch's δ: the paper's estimation error M/N_T (mean)",
            x: "mipmap level",
            y: "M/N_T, % of a window's samples",
            series: series(&|r| 100.0 * r.mnt_mean),
            log_y: false,
            diagonal: false,
            scatter: false,
        },
    )
}

/// Formula 1 beside the accurate blend (`blend.csv`): a chart a measure, against the error
/// asked, a series a scene and blend.
pub fn blend(out: &Path, rows: &[super::blend::Row]) -> Result<(), Fail> {
    fonts();
    let mut keys: Vec<(&str, &str)> = Vec::new();
    for r in rows {
        if !keys.contains(&(r.scene, r.blend)) {
            keys.push((r.scene, r.blend));
        }
    }
    let series = |y: &dyn Fn(&super::blend::Row) -> f64| -> Vec<(String, Vec<(f64, f64)>)> {
        keys.iter()
            .map(|&(scene, blend)| {
                (
                    format!("{scene}, {blend}"),
                    rows.iter()
                        .filter(|r| r.scene == scene && r.blend == blend)
                        .map(|r| (r.error, y(r)))
                        .collect(),
                )
            })
            .collect()
    };
    type Measure<'a> = &'a dyn Fn(&super::blend::Row) -> f64;
    let charts: [(&str, &str, &str, Measure); 4] = [
        (
            "blend_error",
            "Formula 1 and the accurate blend: largest error against the most accurate survey",
            "metres",
            &|r| r.max_err,
        ),
        (
            "blend_jump",
            "Formula 1 and the accurate blend: slope jump along rows, 99th percentile",
            "change of slope between steps (m/m)",
            &|r| r.jump_p99,
        ),
        (
            "blend_patches",
            "Formula 1 and the accurate blend: patches blended per sample",
            "patches (mean)",
            &|r| r.per_sample,
        ),
        (
            "blend_time",
            "Formula 1 and the accurate blend: CPU time per tile",
            "milliseconds (median)",
            &|r| r.cpu_ms,
        ),
    ];
    for (name, title, y, f) in charts {
        both(
            out,
            name,
            &Chart {
                title,
                x: "error asked, e (m)",
                y,
                series: series(f),
                log_y: false,
                diagonal: false,
                scatter: false,
            },
        )?;
    }
    Ok(())
}
