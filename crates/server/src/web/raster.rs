//! Web Mercator XYZ raster tiles: heights resampled at the tile's pixel centres in
//! EPSG:3857 (sample (i, j) at the centre of pixel (i, j), as GDAL writes a raster and as
//! MapLibre reads a DEM tile: it takes pixel (i, j) for the height of the pixel's square and
//! backfills its own one-pixel border from the neighbours), as raster-DEM PNG or float32
//! GeoTIFF.

use super::{Encoding, Produced, Web};
use patchwork_core::geom::tiles::mercator;
use patchwork_core::index::query::Extracted;
use patchwork_core::resample::{Cancel, SampleGrid};
use patchwork_core::terrain::Terrain;
use patchwork_engine::{
    Backend, Ctx, Cut, Engine, EngineError, Heights, Metres, Region, TileRequest,
};
use std::sync::Arc;

/// What a raster tile is encoded as.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// A raster-DEM PNG: heights in the RGB of an encoding MapLibre decodes.
    Png(Encoding),
    /// The same pixels as a lossless WebP, as Mapterhorn publishes terrain.
    Webp(Encoding),
    /// A float32 GeoTIFF in EPSG:3857, voids as its nodata value.
    Tiff,
}

/// A raster tile asked for.
#[derive(Clone, Debug)]
pub struct Request {
    /// The zoom level.
    pub z: u32,
    /// The column, from the west.
    pub x: u32,
    /// The row, from the north.
    pub y: u32,
    /// Pixels on a side: 256 or 512.
    pub size: u32,
    /// What the tile is encoded as.
    pub format: Format,
    /// The cut's error, metres.
    pub error: f64,
    /// What the heights are measured from.
    pub heights: Heights,
}

/// What a GeoTIFF tile says of pixels without data.
const TIFF_NODATA: f64 = -9999.0;

/// The tile `r`: its ETag from the cut, then its bytes unless the client has them.
pub fn tile(
    engine: &Engine,
    web: &Web,
    r: &Request,
    if_none_match: Option<&str>,
    cancel: &Cancel,
) -> Result<Produced, EngineError> {
    let roi = mercator::bounds(r.z, r.x, r.y);
    let crs = web.mercator.clone();
    let (cut, t, ps) = cut_of(engine, web, r)?;
    // The error the tile is made at: the one asked, or a coarser one within the limit.
    let error = cut.error().unwrap_or(r.error);
    let (kind, content_type) = match r.format {
        Format::Png(e) => (e.name(), "image/png"),
        Format::Webp(e) => (e.name(), "image/webp"),
        Format::Tiff => ("tiff", "image/tiff"),
    };
    // The media type is in it: a PNG's tag must not answer for the WebP of the same tile.
    let mut what = format!(
        "raster/{kind}/{content_type}/{}/{}/{}/{}/{:e}",
        r.z, r.x, r.y, r.size, r.error
    );
    if r.heights != Heights::Store {
        // Only then, so that the tags of tiles in the store's frame stay as they were.
        what = format!("{what}/{}", r.heights.key());
    }
    // Refused before any work where the heights cannot be given as asked.
    engine.can_give(&r.heights)?;
    let near = web
        .pyramid(engine)
        .near(&mercator::lonlat_bounds(r.z, r.x, r.y));
    let etag = web.etag(&what, &ps, &near);
    let made = web.produce(etag, if_none_match, content_type, || {
        let size = r.size as usize;
        // Nothing in the cut may still leave voids a survey just beyond the tile fills.
        let empty = ps.is_empty() && near.is_empty();
        let mut heights = if empty {
            vec![f32::NAN; size * size]
        } else {
            let req = TileRequest::new(cut.clone(), r.size, r.size, Backend::Auto)?;
            engine
                .tile(&req, Ctx::until(cancel).with_cut((t, ps)))?
                .0
                .heights
        };
        let grid = SampleGrid::uniform(&roi, size, size);
        let own = cut.crs();
        // Heights in another frame are carried there once the voids are filled, in the
        // store's frame as the surveys are.
        let carry = |heights: &mut Vec<f32>| {
            engine
                .carry_heights(heights, &grid, own, &r.heights)
                .map(|_| ())
        };
        match r.format {
            Format::Png(encoding) | Format::Webp(encoding) => {
                if empty {
                    let webp = matches!(r.format, Format::Webp(_));
                    return Ok(void_image(encoding, webp, r.size));
                }
                // MapLibre reads every pixel as a height, whatever its alpha: voids are
                // filled from coarser levels for it (alpha still says they hold no data),
                // so that hillshade draws no cliff into a hole.
                let voids = engine.fill_voids(&mut heights, &grid, own, error, cancel)?;
                carry(&mut heights)?;
                let pixels = rgba(&heights, &voids, encoding);
                Ok(match r.format {
                    Format::Webp(_) => webp(&pixels, r.size),
                    _ => png(&pixels, r.size),
                })
            }
            Format::Tiff => {
                carry(&mut heights)?;
                let gt = [
                    roi.min[0],
                    roi.width() / r.size as f64,
                    0.0,
                    roi.max[1],
                    0.0,
                    -roi.height() / r.size as f64,
                ];
                patchwork_read::write_tiff::geotiff_f32_bytes(
                    size,
                    size,
                    &heights,
                    gt,
                    Some(&crs),
                    Some(TIFF_NODATA),
                )
                .map_err(|e| EngineError::Encode(format!("a GeoTIFF tile: {e}")))
            }
        }
    })?;
    Ok(Produced {
        error: (error != r.error).then_some(error),
        ..made
    })
}

/// The raster-DEM image the server gives where no survey reaches: every pixel void, as PNG
/// or (`webp`) WebP.
pub fn void_image(encoding: Encoding, webp: bool, size: u32) -> Vec<u8> {
    let n = (size * size) as usize;
    let pixels = rgba(&vec![f32::NAN; n], &vec![true; n], encoding);
    match webp {
        true => self::webp(&pixels, size),
        false => png(&pixels, size),
    }
}

/// The cut of tile `r`, and its patches: at the error asked, or a coarser one where that
/// would take more than `limits.max_web_tile_patches`.
fn cut_of(
    engine: &Engine,
    web: &Web,
    r: &Request,
) -> Result<(Cut, Arc<Terrain>, Vec<Extracted>), EngineError> {
    let crs = web.unless_store(engine, &web.mercator);
    let cut = Cut::uniform(
        crs.clone(),
        Region::new(mercator::bounds(r.z, r.x, r.y))?,
        Metres::error(r.error)?,
    );
    let most = engine.config().limits.max_web_tile_patches;
    if engine.crs().is_none() {
        // A store with no survey yet has nothing anywhere.
        return Ok((cut, engine.snapshot(), Vec::new()));
    }
    match engine.query_within(&cut, most) {
        Err(EngineError::Unreachable { .. }) => {}
        done => return done,
    }
    // A projected store's CRS reaches only part of the tile (a UTM zone's, of a low zoom's
    // tile): the cut is made where the surveys can reach, and the rest of the tile is
    // nodata, as it would be anyway.
    let within = web
        .pyramid(engine)
        .reach_within(&mercator::lonlat_bounds(r.z, r.x, r.y));
    let Some(within) = within else {
        return Ok((cut, engine.snapshot(), Vec::new()));
    };
    let (lo, hi) = (
        mercator::project(within.min[0], within.min[1]),
        mercator::project(within.max[0], within.max[1]),
    );
    let part = Cut::uniform(
        crs.clone(),
        Region::of(lo[0], lo[1], hi[0], hi[1])?,
        Metres::error(r.error)?,
    );
    let (part, t, ps) = engine.query_within(&part, most)?;
    // The tile's cut at the error the part was made at: its samples are the whole tile's.
    let error = Metres::error(part.error().unwrap_or(r.error))?;
    let whole = Cut::uniform(crs, Region::new(mercator::bounds(r.z, r.x, r.y))?, error);
    Ok((whole, t, ps))
}

/// The surveys that served tile `r`, each with the share of the tile's samples it served:
/// `/tiles/{z}/{x}/{y}/sources.json`.
pub fn sources(
    engine: &Engine,
    web: &Web,
    r: &Request,
    cancel: &Cancel,
) -> Result<serde_json::Value, EngineError> {
    let (cut, t, ps) = cut_of(engine, web, r)?;
    let error = cut.error().unwrap_or(r.error);
    let req = TileRequest::new(cut, r.size, r.size, Backend::Auto)?;
    let shares = engine.tile_sources(&req, Ctx::until(cancel).with_cut((t, ps)))?;
    let samples: u64 = shares.iter().map(|s| s.samples).sum();
    let list: Vec<serde_json::Value> = shares
        .iter()
        .map(|s| {
            let mut v = super::source_json(&s.source);
            v["samples"] = s.samples.into();
            v["share"] = s.share.into();
            v
        })
        .collect();
    Ok(serde_json::json!({
        "tile": [r.z, r.x, r.y],
        "size": r.size,
        "error": error,
        "samples": samples,
        "sources": list,
    }))
}

/// The number a height is stored as in an encoding's 24 bits of RGB.
fn code(h: f64, encoding: Encoding) -> u32 {
    let n = match encoding {
        Encoding::Terrarium => (h + 32768.0) * 256.0,
        Encoding::Mapbox => (h + 10000.0) * 10.0,
    };
    n.round().clamp(0.0, (1 << 24) as f64 - 1.0) as u32
}

/// The RGBA pixels of heights in `encoding`: alpha 0 where `voids` says the cut had no data
/// (empty: none), and 0 m in the colour where no height could be found at all.
pub fn rgba(heights: &[f32], voids: &[bool], encoding: Encoding) -> Vec<u8> {
    let mut rgba = Vec::with_capacity(heights.len() * 4);
    for (k, &h) in heights.iter().enumerate() {
        let void = voids.get(k).copied().unwrap_or(false) || h.is_nan();
        let n = code(if h.is_nan() { 0.0 } else { h as f64 }, encoding);
        rgba.extend([
            (n >> 16) as u8,
            (n >> 8) as u8,
            n as u8,
            if void { 0 } else { 255 },
        ]);
    }
    rgba
}

/// A `size²` RGBA PNG of `rgba`.
pub fn png(rgba: &[u8], size: u32) -> Vec<u8> {
    let mut out = Vec::with_capacity(rgba.len() / 3);
    let mut e = png::Encoder::new(&mut out, size, size);
    e.set_color(png::ColorType::Rgba);
    e.set_depth(png::BitDepth::Eight);
    // The fast deflate: a 256² tile in well under a millisecond, at a size near the default's
    // (docs/BENCHMARKS.md, "Web tiles").
    e.set_compression(png::Compression::Fast);
    let mut w = e.write_header().expect("a PNG header in memory");
    w.write_image_data(rgba)
        .expect("as many pixels as the header says, in memory");
    drop(w);
    out
}

/// A `size²` lossless WebP of `rgba`: the same pixels as [`png`]'s, decoded.
pub fn webp(rgba: &[u8], size: u32) -> Vec<u8> {
    let mut cfg = webp::WebPConfig::new().expect("libwebp's default configuration");
    cfg.lossless = 1;
    // Keep the colour of transparent pixels: a void's holds the height filled in for it.
    cfg.exact = 1;
    // In lossless mode, quality is effort: at method 1 and 0 the bytes are within 2% of the
    // most libwebp gets (method 6, 100) in a hundredth of its time. Effort 25 saved 0.2% of
    // the bytes for 15% more time on an export of the Copernicus + NASADEM pair; method 0
    // took half the time but gave 0.83× the PNG's bytes, not 0.59×.
    cfg.method = 1;
    cfg.quality = 0.0;
    webp::Encoder::from_rgba(rgba, size, size)
        .encode_advanced(&cfg)
        .expect("as many pixels as the size says, in memory")
        .to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The decoders MapLibre uses.
    fn decode(rgb: [u8; 3], encoding: Encoding) -> f64 {
        let [r, g, b] = rgb.map(f64::from);
        match encoding {
            Encoding::Terrarium => r * 256.0 + g + b / 256.0 - 32768.0,
            Encoding::Mapbox => -10000.0 + (r * 65536.0 + g * 256.0 + b) * 0.1,
        }
    }

    #[test]
    fn heights_round_trip_through_both_encodings() {
        for h in [-432.1f64, 0.0, 0.001, 1234.567, 8848.86] {
            for (enc, step) in [(Encoding::Terrarium, 1.0 / 256.0), (Encoding::Mapbox, 0.1)] {
                let n = code(h, enc);
                let back = decode([(n >> 16) as u8, (n >> 8) as u8, n as u8], enc);
                assert!((back - h).abs() <= step / 2.0 + 1e-9, "{h} {enc:?} {back}");
            }
        }
    }

    #[test]
    fn webp_tiles_hold_their_pixels_exactly() {
        let heights: Vec<f32> = (0..64 * 64)
            .map(|k| (k % 97) as f32 * 13.7 - 400.0)
            .collect();
        let voids: Vec<bool> = (0..64 * 64).map(|k| k % 11 == 0).collect();
        let pixels = rgba(&heights, &voids, Encoding::Terrarium);
        let bytes = webp(&pixels, 64);
        let mut d = image_webp::WebPDecoder::new(std::io::Cursor::new(bytes)).unwrap();
        assert!(d.has_alpha());
        let mut back = vec![0; d.output_buffer_size().unwrap()];
        d.read_image(&mut back).unwrap();
        // Transparent pixels keep their colour too: MapLibre reads it whatever the alpha.
        assert_eq!(back, pixels);
    }

    #[test]
    fn voids_are_transparent() {
        let pixels = rgba(
            &[100.0, f32::NAN, 200.0, 300.0],
            &[false, true, true, false],
            Encoding::Terrarium,
        );
        let bytes = png(&pixels, 2);
        let d = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut r = d.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size()];
        r.next_frame(&mut buf).unwrap();
        let alpha: Vec<u8> = buf.chunks(4).map(|p| p[3]).collect();
        assert_eq!(alpha, [255, 0, 0, 255]);
        // The filled void keeps its colour; the one with no height at all is 0 m.
        assert_eq!(
            decode([buf[8], buf[9], buf[10]], Encoding::Terrarium),
            200.0
        );
        assert_eq!(decode([buf[4], buf[5], buf[6]], Encoding::Terrarium), 0.0);
    }
}
