//! The GeoTIFF reader against real crops that GDAL wrote and files built to break it.

use super::*;
use crate::test_support::{assert_close, assert_gt_close, data_file};
use crate::write_tiff::{write_geotiff_f32, write_geotiff_i16};
use std::path::PathBuf;

const ARCSEC: f64 = 1.0 / 3600.0;

fn read(path: &Path) -> Result<Raster, ReadError> {
    read_geotiff(path, &ReadLimits::default())
}

fn real(name: &str) -> Raster {
    read(&data_file(name)).unwrap_or_else(|e| panic!("reading {name}: {e}"))
}

// The files below are crops of real surveys that GDAL wrote in the encoding of the file
// each was cut from (tests/data/make_fixtures.py, which printed the figures asserted here).

/// Cut at column 0, row 1650 of the N34 W119 cell, whose tiepoint is on whole degrees.
fn n34w119_crop_geotransform() -> [f64; 6] {
    // PixelIsPoint: GDAL reports the half-pixel shift.
    [
        -119.0 - 0.5 * ARCSEC,
        ARCSEC,
        0.0,
        35.0 + 0.5 * ARCSEC - 1650.0 * ARCSEC,
        0.0,
        -ARCSEC,
    ]
}

#[test]
fn copernicus_cog_tiled_deflate_float_predictor() {
    let r = real("copernicus_cog.tif");
    assert_eq!((r.cols, r.rows), (300, 300));
    assert_eq!(r.crs.epsg(), Some(4326));
    assert_eq!(r.nodata, None);
    assert_gt_close(r.geotransform, n34w119_crop_geotransform(), 1e-12);
    assert_close(r.geotransform[0], -119.000138889, 1e-9, "origin x");
    assert_close(r.geotransform[3], 34.541805556, 1e-9, "origin y");
    assert_eq!(r.nodata_count(), 0);
    let (min, max) = min_max(&r.samples);
    assert_close(min as f64, 190.89943, 1e-4, "min");
    assert_close(max as f64, 1910.6836, 1e-4, "max");
}

#[test]
fn copernicus_tiles_line_up_with_nasadem() {
    // Two independent surveys of the same ground: if any of the 128² tiles were decoded
    // into the wrong place, that tile's typical difference would be hundreds of metres
    // instead of ~0.
    let cop = real("copernicus_cog.tif");
    let nasa = real("nasadem_strips.tif");
    for ty in 0..3 {
        for tx in 0..3 {
            let mut diffs = Vec::new();
            for row in ty * 128..((ty + 1) * 128).min(300) {
                for col in tx * 128..((tx + 1) * 128).min(300) {
                    let d = cop.get(col, row) - nasa.get(col, row);
                    if d.is_finite() {
                        diffs.push(d.abs());
                    }
                }
            }
            let mid = diffs.len() / 2;
            let median = *diffs.select_nth_unstable_by(mid, f32::total_cmp).1;
            assert!(median < 5.0, "tile ({tx},{ty}) median |diff| {median} m");
        }
    }
}

#[test]
fn nasadem_i16_pixel_is_point() {
    let r = real("nasadem_strips.tif");
    assert_eq!((r.cols, r.rows), (300, 300));
    assert_eq!(r.crs.epsg(), Some(4326));
    assert_eq!(r.nodata, Some(-32768.0));
    assert_gt_close(r.geotransform, n34w119_crop_geotransform(), 1e-12);
    assert_eq!(r.nodata_count(), 0, "NASADEM is void-filled");
}

#[test]
fn srtm_utm_projected_epsg_and_voids() {
    let r = real("srtm_utm.tif");
    assert_eq!((r.cols, r.rows), (200, 240));
    assert_eq!(r.crs.epsg(), Some(32631));
    assert_eq!(r.nodata, Some(-32768.0));
    assert_eq!(r.nodata_count(), 3456);
    // PixelIsPoint, 90 m, cut 300 columns in.
    assert_gt_close(
        r.geotransform,
        [
            657641.6582899829 - 45.0 + 300.0 * 90.0,
            90.0,
            0.0,
            4987332.008210683 + 45.0,
            0.0,
            -90.0,
        ],
        1e-6,
    );
}

#[test]
fn philondenx_nodata_zero_and_nan() {
    let r = real("philondenx_zero_nan.tif");
    assert_eq!((r.cols, r.rows), (512, 64));
    assert_eq!(r.crs.epsg(), Some(32630));
    assert_eq!(r.nodata, Some(0.0));
    // 10,124 samples equal to the declared nodata 0 plus one NaN.
    assert_eq!(r.nodata_count(), 10_125);
    assert!(r.get(8, 6).is_nan());
    assert_gt_close(
        r.geotransform,
        [708157.0, 1.0, 0.0, 4827432.0, 0.0, -1.0],
        1e-9,
    );
}

#[test]
fn rhine_deflate_strips_nodata() {
    let r = real("rhine_deflate_strips.tif");
    assert_eq!((r.cols, r.rows), (200, 150));
    assert_eq!(r.crs.epsg(), Some(4326));
    assert_eq!(r.nodata, Some(-9999.0));
    // Part of the rectangle lies outside the basin.
    assert_eq!(r.nodata_count(), 5321);
    assert_gt_close(
        r.geotransform,
        [
            8.566666666495166,
            0.008333333333325754,
            0.0,
            49.50833333330509,
            0.0,
            -0.008333333333339965,
        ],
        1e-9,
    );
}

#[test]
fn lidar_uncompressed_tiles_with_padding() {
    // 200 x 200 in 128 x 128 tiles: the last tile column and row are partly padding.
    let r = real("lidar_tiles_padded.tif");
    assert_eq!((r.cols, r.rows), (200, 200));
    assert_eq!(r.crs.epsg(), Some(26915));
    assert_eq!(r.nodata_count(), 0);
    let (min, max) = min_max(&r.samples);
    assert_close(min as f64, 379.65933, 1e-4, "min");
    assert_close(max as f64, 402.0443, 1e-4, "max");
    // Neighbours across the tile seam at column 128 must be as smooth as inside a tile.
    let seam = (0..200)
        .map(|row| (r.get(128, row) - r.get(127, row)).abs())
        .fold(0f32, f32::max);
    assert!(seam < 1.0, "tile seam jump {seam}");
}

#[test]
fn big_hole_file_has_its_declared_nodata() {
    let r = real("srtm_big_hole.tif");
    assert_eq!((r.cols, r.rows), (200, 200));
    assert_eq!(r.crs.epsg(), Some(4326));
    // The file really declares -32678 (sic), and its holes hold that value.
    assert_eq!(r.nodata, Some(-32678.0));
    assert_eq!(r.nodata_count(), 30_368);
}

fn min_max(v: &[f32]) -> (f32, f32) {
    v.iter()
        .filter(|x| x.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &x| {
            (lo.min(x), hi.max(x))
        })
}

// ---- hand-built TIFFs -------------------------------------------------------------------

enum Val {
    Short(Vec<u16>),
    Long(Vec<u32>),
    Double(Vec<f64>),
    Ascii(&'static str),
}

/// Builds a little-endian classic TIFF holding `chunks` as strips (or tiles when the tags
/// say so); offset/byte-count tags are added here. Lets tests produce layouts, compressions
/// and broken headers that the `tiff` encoder cannot write.
fn build_tiff(tags: Vec<(u16, Val)>, chunks: &[Vec<u8>], tiled: bool) -> Vec<u8> {
    let mut out = b"II*\0\0\0\0\0".to_vec();
    let mut offsets = Vec::new();
    for c in chunks {
        offsets.push(out.len() as u32);
        out.extend_from_slice(c);
    }
    let (off_tag, cnt_tag) = if tiled { (324, 325) } else { (273, 279) };
    let mut tags = tags;
    if !chunks.is_empty() {
        tags.push((off_tag, Val::Long(offsets)));
        tags.push((
            cnt_tag,
            Val::Long(chunks.iter().map(|c| c.len() as u32).collect()),
        ));
    }
    tags.sort_by_key(|t| t.0);
    let encoded: Vec<(u16, u16, u32, Vec<u8>)> = tags
        .into_iter()
        .map(|(tag, v)| match v {
            Val::Short(x) => (
                tag,
                3,
                x.len() as u32,
                x.iter().flat_map(|s| s.to_le_bytes()).collect(),
            ),
            Val::Long(x) => (
                tag,
                4,
                x.len() as u32,
                x.iter().flat_map(|s| s.to_le_bytes()).collect(),
            ),
            Val::Double(x) => (
                tag,
                12,
                x.len() as u32,
                x.iter().flat_map(|s| s.to_le_bytes()).collect(),
            ),
            Val::Ascii(s) => {
                let mut b = s.as_bytes().to_vec();
                b.push(0);
                (tag, 2, b.len() as u32, b)
            }
        })
        .collect();
    let mut value_at = Vec::new();
    for (_, _, _, bytes) in &encoded {
        if bytes.len() > 4 {
            if out.len() % 2 == 1 {
                out.push(0);
            }
            value_at.push(out.len() as u32);
            out.extend_from_slice(bytes);
        } else {
            value_at.push(0);
        }
    }
    if out.len() % 2 == 1 {
        out.push(0);
    }
    let ifd = out.len() as u32;
    out[4..8].copy_from_slice(&ifd.to_le_bytes());
    out.extend_from_slice(&(encoded.len() as u16).to_le_bytes());
    for ((tag, ty, count, bytes), at) in encoded.iter().zip(value_at) {
        out.extend_from_slice(&tag.to_le_bytes());
        out.extend_from_slice(&ty.to_le_bytes());
        out.extend_from_slice(&count.to_le_bytes());
        if bytes.len() > 4 {
            out.extend_from_slice(&at.to_le_bytes());
        } else {
            let mut inline = [0u8; 4];
            inline[..bytes.len()].copy_from_slice(bytes);
            out.extend_from_slice(&inline);
        }
    }
    out.extend_from_slice(&0u32.to_le_bytes());
    out
}

fn geo_tags(origin: (f64, f64), step: f64, epsg: u16) -> Vec<(u16, Val)> {
    vec![
        (33550, Val::Double(vec![step, step, 0.0])),
        (
            33922,
            Val::Double(vec![0.0, 0.0, 0.0, origin.0, origin.1, 0.0]),
        ),
        (
            34735,
            Val::Short(vec![
                1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, epsg,
            ]),
        ),
    ]
}

fn image_tags(w: u32, h: u32, bits: u16, format: u16) -> Vec<(u16, Val)> {
    vec![
        (256, Val::Long(vec![w])),
        (257, Val::Long(vec![h])),
        (258, Val::Short(vec![bits])),
        (262, Val::Short(vec![1])),
        (277, Val::Short(vec![1])),
        (339, Val::Short(vec![format])),
    ]
}

/// A zstd frame made of raw (stored) blocks: valid zstd without needing a compressor.
fn zstd_stored(data: &[u8]) -> Vec<u8> {
    let mut out = vec![0x28, 0xB5, 0x2F, 0xFD];
    // Frame header: single segment, 4-byte content size, no checksum, no dictionary.
    out.push(0b1010_0000);
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    let blocks: Vec<&[u8]> = data.chunks(100_000).collect();
    for (i, b) in blocks.iter().enumerate() {
        let last = u32::from(i + 1 == blocks.len());
        let header = ((b.len() as u32) << 3) | last;
        out.extend_from_slice(&header.to_le_bytes()[..3]);
        out.extend_from_slice(b);
    }
    out
}

/// TIFF floating-point predictor (3) for one row of f32 samples: byte planes, MSB first,
/// then byte-wise horizontal differencing.
fn float_predict_row(row: &[f32]) -> Vec<u8> {
    let n = row.len();
    let mut planes = vec![0u8; n * 4];
    for (i, v) in row.iter().enumerate() {
        for (b, byte) in v.to_be_bytes().iter().enumerate() {
            planes[b * n + i] = *byte;
        }
    }
    for i in (1..planes.len()).rev() {
        planes[i] = planes[i].wrapping_sub(planes[i - 1]);
    }
    planes
}

fn write_temp(dir: &tempfile::TempDir, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.path().join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

#[test]
fn tiled_zstd_float_predictor_with_padding_and_sparse_tile() {
    // 20 x 18 image in 16 x 16 tiles: 2 x 2 tiles, right and bottom ones padded.
    let (w, h, t) = (20usize, 18usize, 16usize);
    let value = |c: usize, r: usize| (r * 100 + c) as f32 + 0.25;
    let mut tiles = Vec::new();
    for ty in 0..2 {
        for tx in 0..2 {
            if (tx, ty) == (1, 1) {
                tiles.push(Vec::new()); // sparse: offset/bytes 0
                continue;
            }
            let mut raw = Vec::new();
            for r in 0..t {
                let row: Vec<f32> = (0..t).map(|c| value(tx * t + c, ty * t + r)).collect();
                raw.extend(float_predict_row(&row));
            }
            tiles.push(zstd_stored(&raw));
        }
    }
    let mut tags = image_tags(w as u32, h as u32, 32, 3);
    tags.extend(geo_tags((500000.0, 4000000.0), 2.0, 32631));
    tags.extend([
        (259, Val::Short(vec![50000])),
        (317, Val::Short(vec![3])),
        (322, Val::Long(vec![t as u32])),
        (323, Val::Long(vec![t as u32])),
        (42113, Val::Ascii("-9999")),
    ]);
    let mut bytes = build_tiff(tags, &tiles, true);
    // build_tiff gave the sparse tile a real offset; GDAL writes 0 for both.
    let pos = find_sparse_offset(&bytes, &tiles);
    bytes[pos..pos + 4].copy_from_slice(&0u32.to_le_bytes());

    let dir = tempfile::tempdir().unwrap();
    let r = read(&write_temp(&dir, "zstd.tif", &bytes)).unwrap();
    assert_eq!((r.cols, r.rows, r.crs.epsg()), (20, 18, Some(32631)));
    assert_eq!(r.geotransform, [500000.0, 2.0, 0.0, 4000000.0, 0.0, -2.0]);
    for row in 0..h {
        for col in 0..w {
            let got = r.get(col, row);
            if col >= t && row >= t {
                assert!(got.is_nan(), "sparse tile sample ({col},{row}) = {got}");
            } else {
                assert_eq!(got, value(col, row), "sample ({col},{row})");
            }
        }
    }
}

#[test]
fn deflated_float_predictor_chunks_decode_as_the_tiff_decoder_does() {
    use std::io::Write;
    // Real heights (the Copernicus crop) with a void, infinities and the nodata value
    // written in, as deflated chunks with the floating-point predictor: 16² tiles with
    // padding on the right and bottom, a sparse tile, and strips of 7 rows.
    let crop =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/copernicus_n34w119_crop.tif");
    let real = read(&crop).unwrap();
    let (w, h) = (45usize, 37usize);
    let value = |c: usize, r: usize| match (c, r) {
        (3, 4) => f32::NAN,
        (10, 2) => f32::INFINITY,
        (11, 30) => f32::NEG_INFINITY,
        (20, 20) => -9999.0,
        _ => real.get(c * 5, r * 7),
    };
    let zlib = |raw: &[u8]| {
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        z.write_all(raw).unwrap();
        z.finish().unwrap()
    };
    let t = 16usize;
    let mut tiles = Vec::new();
    for ty in 0..h.div_ceil(t) {
        for tx in 0..w.div_ceil(t) {
            if (tx, ty) == (2, 0) {
                tiles.push(Vec::new());
                continue;
            }
            let mut raw = Vec::new();
            for r in 0..t {
                let row: Vec<f32> = (0..t)
                    .map(|c| {
                        let (c, r) = (tx * t + c, ty * t + r);
                        if c < w && r < h {
                            value(c, r)
                        } else {
                            1.5
                        }
                    })
                    .collect();
                raw.extend(float_predict_row(&row));
            }
            tiles.push(zlib(&raw));
        }
    }
    let strip_rows = 7usize;
    let strips: Vec<Vec<u8>> = (0..h.div_ceil(strip_rows))
        .map(|s| {
            let mut raw = Vec::new();
            for r in s * strip_rows..((s + 1) * strip_rows).min(h) {
                let row: Vec<f32> = (0..w).map(|c| value(c, r)).collect();
                raw.extend(float_predict_row(&row));
            }
            zlib(&raw)
        })
        .collect();
    let tags = |layout: Vec<(u16, Val)>| {
        let mut tags = image_tags(w as u32, h as u32, 32, 3);
        tags.extend(geo_tags((500000.0, 4000000.0), 30.0, 32611));
        tags.extend([
            (259, Val::Short(vec![8])),
            (317, Val::Short(vec![3])),
            (42113, Val::Ascii("-9999")),
        ]);
        tags.extend(layout);
        tags
    };
    let mut tiled = build_tiff(
        tags(vec![
            (322, Val::Long(vec![t as u32])),
            (323, Val::Long(vec![t as u32])),
        ]),
        &tiles,
        true,
    );
    let pos = find_sparse_offset_at(&tiled, 2);
    tiled[pos..pos + 4].copy_from_slice(&0u32.to_le_bytes());
    let stripped = build_tiff(
        tags(vec![(278, Val::Long(vec![strip_rows as u32]))]),
        &strips,
        false,
    );
    for bytes in [tiled, stripped] {
        let n = bytes.len() as u64;
        let ours = decode_with(&bytes, n, &ReadLimits::default(), true).unwrap();
        let theirs = decode_with(&bytes, n, &ReadLimits::default(), false).unwrap();
        let bits = |r: &Raster| r.samples.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&ours), bits(&theirs));
        assert_eq!(ours.get(0, 0), value(0, 0));
        assert_eq!(ours.get(44, 36), value(44, 36));
        for (c, r) in [(3, 4), (10, 2), (11, 30), (20, 20)] {
            assert!(ours.get(c, r).is_nan(), "({c},{r}) is a void");
        }
    }
    // A chunk that inflates to less than its rows is corrupt, and says which chunk.
    let mut short = tiles.clone();
    short[0] = zlib(&[0u8; 100]);
    let bytes = build_tiff(
        tags(vec![
            (322, Val::Long(vec![t as u32])),
            (323, Val::Long(vec![t as u32])),
        ]),
        &short,
        true,
    );
    let e = decode_with(&bytes, bytes.len() as u64, &ReadLimits::default(), true)
        .unwrap_err()
        .to_string();
    assert!(e.contains("corrupt") && e.contains("chunk 0"), "{e}");
}

/// Position of the last TileOffsets entry, which belongs to the sparse tile in the test above.
fn find_sparse_offset(bytes: &[u8], tiles: &[Vec<u8>]) -> usize {
    find_sparse_offset_at(bytes, tiles.len() - 1)
}

/// Position of TileOffsets entry `k`.
fn find_sparse_offset_at(bytes: &[u8], k: usize) -> usize {
    let ifd = u32::from_le_bytes(bytes[4..8].try_into().unwrap()) as usize;
    let n = u16::from_le_bytes(bytes[ifd..ifd + 2].try_into().unwrap()) as usize;
    for i in 0..n {
        let e = ifd + 2 + i * 12;
        if u16::from_le_bytes(bytes[e..e + 2].try_into().unwrap()) == 324 {
            let at = u32::from_le_bytes(bytes[e + 8..e + 12].try_into().unwrap()) as usize;
            return at + 4 * k;
        }
    }
    panic!("no TileOffsets");
}

#[test]
fn zstd_horizontal_predictor_i16_strips_pixel_is_point_transform() {
    let (w, h) = (5usize, 3usize);
    let values: Vec<i16> = (0..(w * h) as i16).map(|i| i * 37 - 200).collect();
    let mut strips = Vec::new();
    for row in values.chunks(w) {
        let mut raw = Vec::new();
        let mut prev = 0i16;
        for &v in row {
            raw.extend_from_slice(&v.wrapping_sub(prev).to_le_bytes());
            prev = v;
        }
        strips.push(zstd_stored(&raw));
    }
    let mut tags = image_tags(w as u32, h as u32, 16, 2);
    tags.extend([
        (259, Val::Short(vec![50000])),
        (278, Val::Long(vec![1])),
        (317, Val::Short(vec![2])),
        // Rotated ModelTransformation, PixelIsPoint, geographic.
        (
            34264,
            Val::Double(vec![
                0.5, 0.1, 0.0, 10.0, //
                0.2, -0.5, 0.0, 50.0, //
                0.0, 0.0, 0.0, 0.0, //
                0.0, 0.0, 0.0, 1.0,
            ]),
        ),
        (
            34735,
            Val::Short(vec![
                1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 2, 2048, 0, 1, 4326,
            ]),
        ),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let r = read(&write_temp(
        &dir,
        "pred2.tif",
        &build_tiff(tags, &strips, false),
    ))
    .unwrap();
    let expect: Vec<f32> = values.iter().map(|&v| f32::from(v)).collect();
    assert_eq!(r.samples, expect);
    assert_eq!(r.crs.epsg(), Some(4326));
    // GDAL: origin -= half a pixel along both pixel axes.
    assert_gt_close(
        r.geotransform,
        [
            10.0 - 0.5 * (0.5 + 0.1),
            0.5,
            0.1,
            50.0 - 0.5 * (0.2 - 0.5),
            0.2,
            -0.5,
        ],
        1e-12,
    );
}

#[test]
fn encoder_compressions_round_trip() {
    use tiff::encoder::{colortype, Compression, DeflateLevel, TiffEncoder};
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (33u32, 21u32);
    let data: Vec<f32> = (0..w * h).map(|i| (i as f32).sin() * 1000.0).collect();
    for (name, comp) in [
        ("none", Compression::Uncompressed),
        ("lzw", Compression::Lzw),
        ("packbits", Compression::Packbits),
        ("deflate", Compression::Deflate(DeflateLevel::Best)),
    ] {
        let path = dir.path().join(format!("{name}.tif"));
        let file = std::fs::File::create(&path).unwrap();
        let mut enc = TiffEncoder::new(file).unwrap().with_compression(comp);
        let mut img = enc.new_image::<colortype::Gray32Float>(w, h).unwrap();
        img.rows_per_strip(4).unwrap();
        img.encoder()
            .write_tag(Tag::ModelPixelScaleTag, &[1.0f64, 1.0, 0.0][..])
            .unwrap();
        img.encoder()
            .write_tag(
                Tag::ModelTiepointTag,
                &[0.0f64, 0.0, 0.0, 0.0, 21.0, 0.0][..],
            )
            .unwrap();
        img.write_data(&data).unwrap();
        let r = read(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(r.samples, data, "{name}");
        assert_eq!(r.crs.epsg(), None, "{name}");
    }
}

// ---- bad input --------------------------------------------------------------------------

fn expect_err(path: &Path) -> ReadError {
    match read(path) {
        Ok(r) => panic!("{} read without error: {r:?}", path.display()),
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.len() > 20, "unhelpful message {msg:?}");
            e
        }
    }
}

#[test]
fn empty_file_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let e = expect_err(&write_temp(&dir, "empty.tif", b""));
    assert!(e.to_string().contains("empty"), "{e}");
}

#[test]
fn garbage_named_tif_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let garbage: Vec<u8> = (0..4096u32)
        .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
        .collect();
    let e = expect_err(&write_temp(&dir, "garbage.tif", &garbage));
    assert!(e.to_string().contains("not a TIFF"), "{e}");
    let e = expect_err(&write_temp(&dir, "short.tif", b"II*"));
    assert!(
        matches!(e, ReadError::Truncated | ReadError::Invalid { .. }),
        "{e}"
    );
}

#[test]
fn directory_named_tif_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let sub = dir.path().join("x.tif");
    std::fs::create_dir(&sub).unwrap();
    let e = expect_err(&sub);
    assert!(e.to_string().contains("directory"), "{e}");
}

#[test]
fn truncated_real_files_report_truncation() {
    let dir = tempfile::tempdir().unwrap();
    for name in [
        "copernicus_cog.tif",
        "nasadem_strips.tif",
        "rhine_deflate_strips.tif",
    ] {
        let bytes = std::fs::read(data_file(name)).unwrap();
        let cut = write_temp(&dir, name, &bytes[..bytes.len() / 2]);
        let e = expect_err(&cut);
        assert!(matches!(e, ReadError::Truncated), "{name}: {e}");
        assert!(e.to_string().contains("truncated"), "{e}");
    }
    // Cut inside the header itself.
    let bytes = std::fs::read(data_file("rhine_deflate_strips.tif")).unwrap();
    expect_err(&write_temp(&dir, "head.tif", &bytes[..100]));
}

#[test]
fn user_defined_utm_projections_get_their_epsg_code_or_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let tiff = |name: &str, keys: Vec<u16>, doubles: Vec<f64>, ascii: &'static str| {
        let mut tags = image_tags(2, 2, 32, 3);
        tags.push((278, Val::Long(vec![2])));
        tags.push((33550, Val::Double(vec![30.0, 30.0, 0.0])));
        tags.push((
            33922,
            Val::Double(vec![0.0, 0.0, 0.0, 500_000.0, 4_000_000.0, 0.0]),
        ));
        let mut dir_keys = vec![1, 1, 0, (keys.len() / 4) as u16];
        dir_keys.extend(keys);
        tags.push((34735, Val::Short(dir_keys)));
        if !doubles.is_empty() {
            tags.push((34736, Val::Double(doubles)));
        }
        if !ascii.is_empty() {
            tags.push((34737, Val::Ascii(ascii)));
        }
        let strip: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        read(&write_temp(&dir, name, &build_tiff(tags, &[strip], false))).unwrap()
    };
    // ProjectedCSType user-defined, ProjectionGeoKey = UTM zone 31 north, on WGS 84.
    let r = tiff(
        "code.tif",
        vec![
            1024, 0, 1, 1, 2048, 0, 1, 4326, 3072, 0, 1, 32767, 3074, 0, 1, 16031,
        ],
        vec![],
        "",
    );
    assert_eq!((r.crs.epsg(), r.crs.unreadable), (Some(32631), None));
    // Transverse Mercator given by its parameters: UTM 31N.
    let r = tiff(
        "params.tif",
        vec![
            1024, 0, 1, 1, 2048, 0, 1, 4326, 3072, 0, 1, 32767, 3075, 0, 1, 1, 3080, 34736, 1, 0,
            3081, 34736, 1, 1, 3082, 34736, 1, 2, 3083, 34736, 1, 3, 3092, 34736, 1, 4,
        ],
        vec![3.0, 0.0, 500_000.0, 0.0, 0.9996],
        "",
    );
    assert_eq!(r.crs.epsg(), Some(32631));
    // Only a citation, as GDAL writes for a WKT it cannot encode: UTM 33S on WGS 84.
    let r = tiff(
        "cited.tif",
        vec![1024, 0, 1, 1, 1026, 34737, 22, 0, 3072, 0, 1, 32767],
        vec![],
        "WGS 84 / UTM zone 33S|",
    );
    assert_eq!(r.crs.epsg(), Some(32733));
    // A projection we do not know is named, not reported as missing.
    let r = tiff(
        "lambert.tif",
        vec![
            1024, 0, 1, 1, 1026, 34737, 19, 0, 3072, 0, 1, 32767, 3075, 0, 1, 8,
        ],
        vec![],
        "RGF93 / Lambert-93|",
    );
    assert_eq!(r.crs.epsg(), None);
    assert_eq!(r.crs.unreadable.as_deref(), Some("RGF93 / Lambert-93"));
}

#[test]
fn huge_header_is_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let mut tags = image_tags(1_000_000, 1_000_000, 32, 3);
    tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
    tags.push((278, Val::Long(vec![1_000_000])));
    // One strip whose data is missing entirely.
    let bytes = build_tiff(tags, &[vec![0u8; 16]], false);
    let e = expect_err(&write_temp(&dir, "huge.tif", &bytes));
    assert!(
        matches!(
            e,
            ReadError::TooLarge {
                cols: 1_000_000,
                rows: 1_000_000,
                ..
            }
        ),
        "{e}"
    );

    // The same claim with no strip or tile tags at all.
    let bytes = build_tiff(image_tags(1_000_000, 1_000_000, 32, 3), &[], false);
    let e = expect_err(&write_temp(&dir, "huge_nodata.tif", &bytes));
    assert!(matches!(e, ReadError::Invalid { .. }), "{e}");

    // Tighter caller limits apply too.
    let small = write_temp(&dir, "small.tif", &small_geotiff_bytes(&dir));
    let e = read_geotiff(
        &small,
        &ReadLimits {
            max_bytes: 40,
            roots: None,
        },
    )
    .unwrap_err();
    assert!(matches!(e, ReadError::TooLarge { .. }), "{e}");
}

#[test]
fn a_few_bytes_claiming_a_huge_raster_are_refused_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let raster = |w: u32, compression: u16| {
        let mut tags = image_tags(w, w, 32, 3);
        tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
        tags.push((259, Val::Short(vec![compression])));
        tags.push((278, Val::Long(vec![w])));
        tags
    };
    // One sparse strip: StripOffsets = 0, StripByteCounts = 0.
    let mut tags = raster(20_000, 1);
    tags.push((273, Val::Long(vec![0])));
    tags.push((279, Val::Long(vec![0])));
    let bytes = build_tiff(tags, &[], false);
    assert!(bytes.len() < 300, "{} bytes", bytes.len());
    // Refused by the header's own figures, before any strip is read or any buffer made: the
    // message is the check's, which runs before both.
    let e = expect_err(&write_temp(&dir, "sparse.tif", &bytes));
    assert!(e.to_string().contains("can fill at most 0"), "{e}");
    // A compressed strip can only expand so far: 16 bytes of zstd fill 128 Ki samples.
    let bytes = build_tiff(raster(20_000, 50000), &[vec![0u8; 16]], false);
    let e = expect_err(&write_temp(&dir, "zstd.tif", &bytes));
    assert!(e.to_string().contains("can fill at most 131072"), "{e}");
    // Many strips that point at the same bytes hold those bytes once: 2,000 strips of a
    // row each, all at the one 8 KB row at offset 8 (the offsets array itself, the first
    // value written there), cannot fill 2000 × 2000 samples.
    let mut tags = image_tags(2000, 2000, 32, 3);
    tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
    tags.push((278, Val::Long(vec![1])));
    tags.push((273, Val::Long(vec![8; 2000])));
    tags.push((279, Val::Long(vec![8000; 2000])));
    let bytes = build_tiff(tags, &[], false);
    assert!(bytes.len() < 20_000);
    let e = expect_err(&write_temp(&dir, "overlap.tif", &bytes));
    assert!(e.to_string().contains("can fill at most"), "{e}");
    // A raster small enough to cost nothing is still read, sparse or not.
    let mut tags = raster(64, 1);
    tags.push((273, Val::Long(vec![0])));
    tags.push((279, Val::Long(vec![0])));
    let r = read(&write_temp(
        &dir,
        "small.tif",
        &build_tiff(tags, &[], false),
    ))
    .unwrap();
    assert_eq!((r.cols, r.rows), (64, 64));
}

#[test]
fn unsupported_sample_types_and_bands_are_named() {
    use tiff::encoder::{colortype, TiffEncoder};
    let dir = tempfile::tempdir().unwrap();

    let rgb = dir.path().join("rgb.tif");
    TiffEncoder::new(std::fs::File::create(&rgb).unwrap())
        .unwrap()
        .write_image::<colortype::RGB8>(4, 4, &[7u8; 48])
        .unwrap();
    let e = expect_err(&rgb);
    assert!(matches!(e, ReadError::Unsupported { .. }), "{e}");
    assert!(e.to_string().contains("3 bands"), "{e}");

    let u64_path = dir.path().join("u64.tif");
    TiffEncoder::new(std::fs::File::create(&u64_path).unwrap())
        .unwrap()
        .write_image::<colortype::Gray64>(4, 4, &[7u64; 16])
        .unwrap();
    let e = expect_err(&u64_path);
    assert!(e.to_string().contains("64-bit unsigned integer"), "{e}");

    // Hand-made complex float file; the decoder itself cannot represent it.
    let mut tags = image_tags(2, 2, 64, 6);
    tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
    let bytes = build_tiff(tags, &[vec![0u8; 32]], false);
    let e = expect_err(&write_temp(&dir, "complex.tif", &bytes));
    assert!(e.to_string().contains("complex floating point"), "{e}");
}

#[test]
fn plain_tiff_without_georeference_is_refused() {
    use tiff::encoder::{colortype, TiffEncoder};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plain.tif");
    TiffEncoder::new(std::fs::File::create(&path).unwrap())
        .unwrap()
        .write_image::<colortype::GrayI16>(3, 3, &[1i16; 9])
        .unwrap();
    let e = expect_err(&path);
    assert!(e.to_string().contains("no usable georeferencing"), "{e}");
}

#[test]
fn bad_nodata_tag_is_reported() {
    let mut tags = image_tags(2, 1, 16, 2);
    tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
    tags.push((42113, Val::Ascii("none")));
    let dir = tempfile::tempdir().unwrap();
    let bytes = build_tiff(tags, &[vec![1, 0, 2, 0]], false);
    let e = expect_err(&write_temp(&dir, "nd.tif", &bytes));
    assert!(e.to_string().contains("GDAL_NODATA"), "{e}");
}

#[test]
fn infinities_become_nan_and_nodata_whitespace_is_trimmed() {
    let mut tags = image_tags(4, 1, 32, 3);
    tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
    tags.push((42113, Val::Ascii(" -3.4028234663852886e+38 \n")));
    let data: Vec<u8> = [f32::INFINITY, f32::NEG_INFINITY, f32::MIN, 12.5]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let r = read(&write_temp(
        &dir,
        "inf.tif",
        &build_tiff(tags, &[data], false),
    ))
    .unwrap();
    assert_eq!(r.nodata, Some(f64::from(f32::MIN)));
    assert!(r.samples[..3].iter().all(|v| v.is_nan()), "{:?}", r.samples);
    assert_eq!(r.samples[3], 12.5);
}

fn small_geotiff_bytes(dir: &tempfile::TempDir) -> Vec<u8> {
    let path = dir.path().join("seed.tif");
    let samples: Vec<f32> = (0..64).map(|i| i as f32 * 1.5).collect();
    write_geotiff_f32(
        &path,
        8,
        8,
        &samples,
        [600000.0, 30.0, 0.0, 5000000.0, 0.0, -30.0],
        Some(&patchwork_crs::Crs::epsg(32631).unwrap()),
        Some(-9999.0),
    )
    .unwrap();
    std::fs::read(path).unwrap()
}

#[test]
fn corrupted_bytes_never_panic_out() {
    // Deterministic mutation fuzzing of a valid file: every outcome must be Ok or Err.
    let dir = tempfile::tempdir().unwrap();
    let seed = small_geotiff_bytes(&dir);
    let i16_path = dir.path().join("seed16.tif");
    write_geotiff_i16(
        &i16_path,
        4,
        4,
        &[5i16; 16],
        [0.0, 1.0, 0.0, 4.0, 0.0, -1.0],
        Some(&patchwork_crs::Crs::epsg(4326).unwrap()),
        None,
    )
    .unwrap();
    let seeds = [seed, std::fs::read(&i16_path).unwrap()];
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let path = dir.path().join("fuzz.tif");
    for i in 0..400 {
        let mut bytes = seeds[i % 2].clone();
        for _ in 0..1 + next() % 4 {
            let pos = (next() % bytes.len() as u64) as usize;
            bytes[pos] = next() as u8;
        }
        if next() % 5 == 0 {
            let keep = (next() % bytes.len() as u64) as usize;
            bytes.truncate(keep.max(1));
        }
        std::fs::write(&path, &bytes).unwrap();
        let _ = read(&path);
    }
}

#[test]
fn the_acquisition_date_comes_from_gdal_metadata_else_the_tiff_date() {
    let dir = tempfile::tempdir().unwrap();
    let file = |name: &str, extra: Vec<(u16, Val)>| {
        let mut tags = image_tags(2, 1, 16, 2);
        tags.extend(geo_tags((0.0, 0.0), 1.0, 32631));
        tags.extend(extra);
        read(&write_temp(
            &dir,
            name,
            &build_tiff(tags, &[vec![1, 0, 2, 0]], false),
        ))
        .unwrap()
        .acquired
    };
    let xml = "<GDALMetadata>\n  <Item name=\"AREA_OR_POINT\">Area</Item>\n  \
               <Item name=\"ACQUISITION_DATE\">2011-02-11</Item>\n</GDALMetadata>\n";
    assert_eq!(
        file(
            "both.tif",
            vec![
                (306, Val::Ascii("2019:05:03 10:00:00")),
                (42112, Val::Ascii(xml))
            ]
        )
        .as_deref(),
        Some("2011-02-11")
    );
    // An item that is no date is passed over for the TIFF's own.
    let vague = "<GDALMetadata><Item name=\"DATE_ACQUIRED\">unknown</Item></GDALMetadata>";
    assert_eq!(
        file(
            "vague.tif",
            vec![
                (306, Val::Ascii("2019:05:03 10:00:00")),
                (42112, Val::Ascii(vague))
            ]
        )
        .as_deref(),
        Some("2019:05:03 10:00:00")
    );
    assert_eq!(file("none.tif", vec![]), None);
    assert_eq!(file("bad.tif", vec![(306, Val::Ascii("yesterday"))]), None);
}
