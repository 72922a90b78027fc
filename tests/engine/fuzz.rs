//! Fuzzing on stable Rust: byte mutations of real files drive each reader (GeoTIFF, SRTM .hgt,
//! ESRI ASCII grid with its .prj) and the sidecar parser. Every input must end in `Ok` or
//! `Err`: no panic, no allocation past the limit, no hang.
//!
//! The suite runs a few thousand inputs a target. The campaign docs/RELIABILITY.md reports is
//! the same code run longer:
//!
//! ```text
//! PATCHWORK_FUZZ_INPUTS=1000000 cargo test --release --test engine fuzz:: -- --nocapture
//! ```
//!
//! Mutations are deterministic (a seeded xorshift), so a failure names the target and the
//! input number that reproduce it; `PATCHWORK_FUZZ_START` starts a run there.

use patchwork::ingest::parse_sidecar;
use patchwork_read::{read_raster, ReadLimits};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;
use std::time::{Duration, Instant};

/// Counts the bytes this thread holds, and the most it held, so that each input's peak is
/// its own.
struct Counting;

thread_local! {
    static HELD: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn note(delta: isize) {
    let _ = HELD.try_with(|h| {
        let v = h.get() + delta;
        h.set(v);
        let _ = PEAK.try_with(|p| p.set(p.get().max(v)));
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(l) };
        if !p.is_null() {
            note(l.size() as isize);
        }
        p
    }

    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(l) };
        if !p.is_null() {
            note(l.size() as isize);
        }
        p
    }

    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) };
        note(-(l.size() as isize));
    }

    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        let q = unsafe { System.realloc(p, l, new) };
        if !q.is_null() {
            note(new as isize - l.size() as isize);
        }
        q
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Bytes `f` allocated at its peak, beyond what the thread held before.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, u64) {
    let base = HELD.with(Cell::get);
    PEAK.with(|p| p.set(base));
    let out = f();
    (out, (PEAK.with(Cell::get) - base).max(0) as u64)
}

/// What the readers may decode into: the limit each input is held to.
const MAX_INGEST_MB: u64 = 64;
/// Longest any one input may take before it counts as a hang.
const HANG: Duration = Duration::from_secs(2);

/// A raster of at most `MAX_INGEST_MB`, plus one decoded chunk as large, plus a few times the
/// file itself (read buffers, the compressed chunk) and a little for the rest.
fn allowed(input_len: usize) -> u64 {
    2 * (MAX_INGEST_MB << 20) + 4 * input_len as u64 + (8 << 20)
}

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
}

/// Values that sit on the edges parsers get wrong.
const INTERESTING: [u64; 14] = [
    0,
    1,
    2,
    0x7f,
    0x80,
    0xff,
    0x7fff,
    0x8000,
    0xffff,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    0x7fff_ffff_ffff_ffff,
    u64::MAX,
];

/// One havoc step on `b`, with `other` to splice from.
fn mutate(b: &mut Vec<u8>, other: &[u8], r: &mut Rng) {
    if b.is_empty() {
        b.push(r.next() as u8);
        return;
    }
    let pos = r.below(b.len());
    match r.below(10) {
        0 => b[pos] ^= 1 << r.below(8),
        1 => b[pos] = r.next() as u8,
        2 => b[pos] = INTERESTING[r.below(6)] as u8,
        3 | 4 => {
            // A 2, 4 or 8 byte field set to an edge value or near the file's length, in
            // either byte order: TIFF counts and offsets.
            let width = [2usize, 4, 8][r.below(3)];
            let v = if r.below(3) == 0 {
                (b.len() as u64)
                    .wrapping_add(r.below(16) as u64)
                    .wrapping_sub(8)
            } else {
                INTERESTING[r.below(INTERESTING.len())]
            };
            let bytes = if r.below(2) == 0 {
                v.to_le_bytes()
            } else {
                v.to_be_bytes()
            };
            let end = (pos + width).min(b.len());
            let src = if bytes[0] == 0 && width < 8 {
                &bytes[8 - width..]
            } else {
                &bytes[..width]
            };
            b[pos..end].copy_from_slice(&src[..end - pos]);
        }
        5 => {
            let n = 1 + r.below(64.min(b.len() - pos));
            b.drain(pos..pos + n);
        }
        6 => {
            let n = 1 + r.below(64);
            let fill: Vec<u8> = (0..n).map(|_| r.next() as u8).collect();
            b.splice(pos..pos, fill);
        }
        7 => {
            let n = 1 + r.below(256.min(b.len() - pos));
            let piece = b[pos..pos + n].to_vec();
            let at = r.below(b.len());
            b.splice(at..at, piece);
        }
        8 => b.truncate(pos),
        _ => {
            if !other.is_empty() {
                let cut = r.below(other.len());
                b.truncate(pos);
                b.extend_from_slice(&other[cut..]);
            }
        }
    }
}

/// Replaces a whitespace-separated word with one that text parsers get wrong.
fn mutate_word(b: &mut Vec<u8>, r: &mut Rng) {
    const WORDS: [&str; 16] = [
        "0",
        "-1",
        "1e308",
        "-1e308",
        "nan",
        "inf",
        "99999999999999999999",
        "4294967297",
        "0.0000001",
        "-0",
        "ncols",
        "nrows",
        "cellsize",
        "NODATA_value",
        "",
        "1,5",
    ];
    let starts: Vec<usize> = (0..b.len())
        .filter(|&i| !b[i].is_ascii_whitespace() && (i == 0 || b[i - 1].is_ascii_whitespace()))
        .collect();
    if starts.is_empty() {
        return;
    }
    let s = starts[r.below(starts.len())];
    let e = (s..b.len())
        .find(|&i| b[i].is_ascii_whitespace())
        .unwrap_or(b.len());
    b.splice(s..e, WORDS[r.below(WORDS.len())].bytes());
}

#[derive(Default, Debug)]
struct Tally {
    inputs: u64,
    ok: u64,
    slowest: Duration,
    most_bytes: u64,
}

/// Runs `count` inputs made from `seeds` through `run`, which returns whether the input was
/// accepted; checks the allocation bound and the time of each.
fn campaign(
    target: &str,
    seeds: &[Vec<u8>],
    words: bool,
    mut run: impl FnMut(&[u8], &mut Rng) -> bool,
) -> Tally {
    let count: u64 = std::env::var("PATCHWORK_FUZZ_INPUTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(4000);
    let start: u64 = std::env::var("PATCHWORK_FUZZ_START")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    let mut t = Tally::default();
    let t0 = Instant::now();
    for i in start..start + count {
        let mut r = Rng(0x9E37_79B9_7F4A_7C15 ^ (i.wrapping_mul(0x2545_F491_4F6C_DD1D)) | 1);
        let mut input = seeds[r.below(seeds.len())].clone();
        let other = &seeds[r.below(seeds.len())];
        // Half the inputs are one step from a seed, so that parsing gets past the header.
        let steps = if r.below(2) == 0 { 1 } else { 2 + r.below(7) };
        for _ in 0..steps {
            if words && r.below(3) == 0 {
                mutate_word(&mut input, &mut r);
            } else {
                mutate(&mut input, other, &mut r);
            }
        }
        let began = Instant::now();
        let (result, bytes) = peak_of(|| {
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(&input, &mut r)))
        });
        let took = began.elapsed();
        let accepted = result.unwrap_or_else(|_| panic!("{target}: input {i} panicked"));
        assert!(
            bytes <= allowed(input.len()),
            "{target}: input {i} allocated {bytes} bytes from a file of {}",
            input.len()
        );
        assert!(took < HANG, "{target}: input {i} took {took:?}");
        t.inputs += 1;
        t.ok += u64::from(accepted);
        t.slowest = t.slowest.max(took);
        t.most_bytes = t.most_bytes.max(bytes);
    }
    eprintln!(
        "fuzz {target}: {} inputs in {:.1} s, {} accepted, slowest {:.1} ms, most memory {:.1} MiB",
        t.inputs,
        t0.elapsed().as_secs_f64(),
        t.ok,
        t.slowest.as_secs_f64() * 1e3,
        t.most_bytes as f64 / (1 << 20) as f64
    );
    t
}

fn crop(name: &str) -> Vec<u8> {
    std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(name),
    )
    .unwrap()
}

fn limits() -> ReadLimits {
    ReadLimits::mb(MAX_INGEST_MB)
}

/// Writes `bytes` to `path` and reads it back as a raster.
fn read_as(path: &Path, bytes: &[u8]) -> bool {
    std::fs::write(path, bytes).unwrap();
    read_raster(path, &limits()).is_ok()
}

fn small_tiffs(dir: &Path) -> Vec<Vec<u8>> {
    use patchwork_read::{write_geotiff_f32, write_geotiff_i16};
    let f = dir.join("f.tif");
    let samples: Vec<f32> = (0..64).map(|i| i as f32 * 1.5).collect();
    let gt = [600000.0, 30.0, 0.0, 5000000.0, 0.0, -30.0];
    write_geotiff_f32(
        &f,
        8,
        8,
        &samples,
        gt,
        Some(&patchwork_core::crs::Crs::epsg(32631).unwrap()),
        Some(-9999.0),
    )
    .unwrap();
    let i = dir.join("i.tif");
    let gt = [5.0, 0.001, 0.0, 45.0, 0.0, -0.001];
    write_geotiff_i16(
        &i,
        4,
        4,
        &[5i16; 16],
        gt,
        Some(&patchwork_core::crs::Crs::epsg(4326).unwrap()),
        None,
    )
    .unwrap();
    vec![std::fs::read(f).unwrap(), std::fs::read(i).unwrap()]
}

#[test]
fn geotiff_reader() {
    let dir = tempfile::tempdir().unwrap();
    let mut seeds = small_tiffs(dir.path());
    // Real files: tiled deflate with a float predictor (a COG), strips, voids, a sparse hole.
    for name in [
        "copernicus_n34w119_crop.tif",
        "nasadem_n34w119_crop.tif",
        "srtm_n44e005_voids_crop.tif",
        "srtm_n44e005_big_hole_crop.tif",
    ] {
        seeds.push(crop(name));
    }
    let path = dir.path().join("input.tif");
    let t = campaign("geotiff", &seeds, false, |b, _| read_as(&path, b));
    assert!(
        t.ok > 0,
        "no input was read at all: the mutations are too wild"
    );
}

/// An SRTM3 tile's bytes: a big-endian i16 landscape with a void.
fn hgt_tile() -> Vec<u8> {
    let n = 1201;
    let mut b = Vec::with_capacity(n * n * 2);
    for r in 0..n {
        for c in 0..n {
            let z = if (r as i32 - 600).pow(2) + (c as i32 - 600).pow(2) < 400 {
                -32768
            } else {
                (800.0 + 300.0 * ((r as f64) / 90.0).sin() * ((c as f64) / 70.0).cos()) as i16
            };
            b.extend_from_slice(&z.to_be_bytes());
        }
    }
    b
}

#[test]
fn hgt_reader() {
    let dir = tempfile::tempdir().unwrap();
    let tile = hgt_tile();
    // Small seeds exercise the name and size checks quickly; the full tile, less often, the
    // samples.
    let seeds = vec![tile[..4096].to_vec(), vec![0u8; 2], b"N44E005".to_vec()];
    const NAMES: [&str; 8] = [
        "N44E005.hgt",
        "s12w077.SRTMGL1.hgt",
        "N90E000.hgt",
        "S90W180.hgt",
        "X44E005.hgt",
        "N4E005.hgt",
        "n00e180.hgt",
        "N44E005.HGT",
    ];
    let t = campaign("hgt", &seeds, false, |b, r| {
        let name = NAMES[r.below(NAMES.len())];
        let path = dir.path().join(name);
        if r.below(50) == 0 {
            // A tile of the right size, its samples mutated in place.
            let mut full = tile.clone();
            for _ in 0..1 + r.below(64) {
                let at = r.below(full.len());
                full[at] = r.next() as u8;
            }
            read_as(&path, &full)
        } else {
            read_as(&path, b)
        }
    });
    assert!(t.ok > 0);
}

#[test]
fn ascii_reader_and_its_prj() {
    let dir = tempfile::tempdir().unwrap();
    let seeds: Vec<Vec<u8>> = [
        "ncols 4\nnrows 3\nxllcorner 500000\nyllcorner 4000000\ncellsize 30\nNODATA_value -9999\n1 2 3 4\n5 -9999 7 8\n9 10 11 12\n",
        "NCOLS 2\nNROWS 2\nXLLCENTER 5.5\nYLLCENTER 44.5\nDX 0.1\nDY 0.2\n1.5 nan\n3e1 4\n",
        "ncols 3\nnrows 1\nxllcorner -1\nyllcorner -1\ncellsize 1e-3\n0 0 0\n",
    ]
    .iter()
    .map(|s| s.as_bytes().to_vec())
    .collect();
    let prjs = [
        r#"PROJCS["WGS_1984_UTM_Zone_31N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",3.0],PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]"#,
        r#"GEOGCS["WGS 84",AUTHORITY["EPSG","4326"]]"#,
        "EPSG:4326",
    ];
    let grid = dir.path().join("input.asc");
    let prj = dir.path().join("input.prj");
    let t = campaign("ascii", &seeds, true, |b, r| {
        if r.below(4) == 0 {
            let mut p = prjs[r.below(prjs.len())].as_bytes().to_vec();
            for _ in 0..r.below(4) {
                mutate(&mut p, b"", r);
            }
            std::fs::write(&prj, p).unwrap();
        } else {
            let _ = std::fs::remove_file(&prj);
        }
        read_as(&grid, b)
    });
    assert!(t.ok > 0);
}

#[test]
fn sidecar_parser() {
    let seeds: Vec<Vec<u8>> = [
        "accuracy_m = 2.5\n",
        "crs = \"EPSG:4326\"\naccuracy_m = 0.5\n",
        "# a comment\naccuracy_m = 1e3 # inline\n",
        "crs = 'epsg:32631'\n",
    ]
    .iter()
    .map(|s| s.as_bytes().to_vec())
    .collect();
    let t = campaign("sidecar", &seeds, true, |b, _| match parse_sidecar(b) {
        Ok(s) => {
            if let Some(c) = &s.crs {
                let _ = patchwork::config::parse_epsg(c);
            }
            true
        }
        Err(e) => {
            assert!(!e.is_empty());
            false
        }
    });
    assert!(t.ok > 0);
}
