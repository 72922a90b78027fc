//! Readers that turn elevation files (GeoTIFF/COG, SRTM `.hgt`, ESRI ASCII grid) into a
//! [`Raster`], plus a small GeoTIFF writer used for exports and test fixtures.

pub mod ascii;
pub mod crs;
pub mod geotiff;
pub mod gtx;
pub mod hgt;
pub mod write_cog;
pub mod write_npy;
pub mod write_tiff;

use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub use ascii::AsciiGridReader;
pub use geotiff::GeoTiffReader;
pub use hgt::HgtReader;
pub use write_npy::write_npy;
pub use write_tiff::{write_geotiff_f32, write_geotiff_i16};

/// A raster as read from a file, before it becomes a model Grid.
#[derive(Clone)]
pub struct Raster {
    /// Samples a row.
    pub cols: usize,
    /// Rows of samples.
    pub rows: usize,
    /// Row-major, row 0 is the first row in the file (north for north-up rasters). Nodata samples are f32::NAN.
    pub samples: Vec<f32>,
    /// Georeference, GDAL convention: world = (a, b, c, d, e, f) affine where
    /// x = gt[0] + col*gt[1] + row*gt[2],  y = gt[3] + col*gt[4] + row*gt[5]
    /// giving the OUTER CORNER of pixel (col,row) (PixelIsArea convention). For PixelIsPoint files convert so that
    /// the sample (col,row) sits at the pixel centre of the returned transform, exactly as GDAL does
    /// (shift the origin by -0.5 pixel in both axes).
    pub geotransform: [f64; 6],
    /// The CRS the file gives, if any: the horizontal CRS, a vertical one where it names
    /// one, and what it describes that could not be read.
    pub crs: crs::FileCrs,
    /// The declared nodata value if any (already applied: such samples are NaN in `samples`).
    pub nodata: Option<f64>,
    /// When the file says its survey was acquired, as it says it (a GDAL metadata item that
    /// names an acquisition date, else TIFF's `DateTime`), where that is a date
    /// [`patchwork_model::epoch::Epoch`] reads; None where it says nothing usable.
    pub acquired: Option<String>,
}

impl Raster {
    /// The sample at (`col`, `row`), NaN for nodata. Panics when out of range, like slice indexing.
    pub fn get(&self, col: usize, row: usize) -> f32 {
        assert!(
            col < self.cols && row < self.rows,
            "({col}, {row}) outside raster"
        );
        self.samples[row * self.cols + col]
    }

    /// Number of nodata (NaN) samples.
    pub fn nodata_count(&self) -> usize {
        self.samples.iter().filter(|v| v.is_nan()).count()
    }

    /// World coordinates of the centre of pixel (`col`, `row`).
    pub fn pixel_centre(&self, col: usize, row: usize) -> (f64, f64) {
        let (c, r) = (col as f64 + 0.5, row as f64 + 0.5);
        let gt = &self.geotransform;
        (gt[0] + c * gt[1] + r * gt[2], gt[3] + c * gt[4] + r * gt[5])
    }
}

impl Raster {
    /// The raster as a model grid. Fails for degenerate georeferences and rasters of fewer
    /// than 2×2 samples.
    pub fn into_grid(
        self,
    ) -> Result<patchwork_model::grid::Grid, patchwork_model::grid::GridError> {
        let georef = patchwork_model::grid::Georef::from_geotransform(self.geotransform)?;
        patchwork_model::grid::Grid::new(self.cols, self.rows, self.samples, georef)
    }

    /// A window of the raster, georeferenced where it lies.
    pub fn crop(&self, col: usize, row: usize, cols: usize, rows: usize) -> Raster {
        assert!(
            col + cols <= self.cols && row + rows <= self.rows,
            "crop outside raster"
        );
        let samples = (row..row + rows)
            .flat_map(|r| {
                self.samples[r * self.cols + col..r * self.cols + col + cols]
                    .iter()
                    .copied()
            })
            .collect();
        let gt = self.geotransform;
        let (c, r) = (col as f64, row as f64);
        Raster {
            cols,
            rows,
            samples,
            geotransform: [
                gt[0] + c * gt[1] + r * gt[2],
                gt[1],
                gt[2],
                gt[3] + c * gt[4] + r * gt[5],
                gt[4],
                gt[5],
            ],
            crs: self.crs.clone(),
            nodata: self.nodata,
            acquired: self.acquired.clone(),
        }
    }
}

impl std::fmt::Debug for Raster {
    // The sample vector can hold billions of values; printing it would drown every assertion message.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Raster")
            .field("cols", &self.cols)
            .field("rows", &self.rows)
            .field("geotransform", &self.geotransform)
            .field("crs", &self.crs.crs)
            .field("nodata", &self.nodata)
            .finish_non_exhaustive()
    }
}

/// Why a raster file could not be read (or written).
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file ends before all the data its header describes.
    #[error("the file is truncated: it ends before all the data its header describes")]
    Truncated,
    /// A raster of a kind this reader does not read (a sample format, a compression).
    #[error("unsupported raster: {what}")]
    Unsupported {
        /// What is not supported.
        what: String,
    },
    /// A file that is not a valid raster of its format.
    #[error("invalid raster file: {what}")]
    Invalid {
        /// What is wrong.
        what: String,
    },
    /// A raster whose samples need more memory than the limit.
    #[error(
        "raster is too large: {cols} x {rows} samples need more memory than the limit of \
         {limit_mb} MiB (limits.max_ingest_mb)"
    )]
    TooLarge {
        /// Its samples a row.
        cols: u64,
        /// Its rows.
        rows: u64,
        /// The limit, in MiB.
        limit_mb: u64,
    },
    /// The file, or one beside it, does not resolve inside the folders it may be read from.
    #[error("{}", REFUSED_PATH)]
    Outside,
    /// Reading the file failed.
    #[error("I/O error: {0}")]
    Io(#[source] std::io::Error),
}

/// The one message for a path that may not be read, whatever is or is not there: a client
/// must not learn about files outside the folders it was given.
pub const REFUSED_PATH: &str = "not a file this daemon may ingest: a path must lead, symlinks \
     followed, to a file inside the inbox folders or ingest_roots";

impl From<std::io::Error> for ReadError {
    // Every reader hits end-of-file the same way on a cut-off download; give it one clear name.
    fn from(e: std::io::Error) -> Self {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            ReadError::Truncated
        } else {
            ReadError::Io(e)
        }
    }
}

impl ReadError {
    pub(crate) fn invalid(what: impl Into<String>) -> Self {
        ReadError::Invalid { what: what.into() }
    }

    pub(crate) fn unsupported(what: impl Into<String>) -> Self {
        ReadError::Unsupported { what: what.into() }
    }
}

/// What reading an untrusted file may cost, and where it may read.
#[derive(Clone, Debug)]
pub struct ReadLimits {
    /// Most bytes the decoded raster (`f32` samples) may take. Checked against the header
    /// before any sample buffer exists.
    pub max_bytes: u64,
    /// Resolved folders that every file read (the raster and the files beside it) must lie
    /// in; `None` reads anywhere.
    pub roots: Option<Arc<[PathBuf]>>,
}

impl Default for ReadLimits {
    fn default() -> Self {
        ReadLimits {
            max_bytes: 4 << 30,
            roots: None,
        }
    }
}

/// Bytes of the decoded raster, which holds one `f32` a sample.
const SAMPLE_BYTES: u64 = 4;

impl ReadLimits {
    /// Limits of `mb` mebibytes.
    pub fn mb(mb: u64) -> Self {
        ReadLimits {
            max_bytes: mb.saturating_mul(1 << 20),
            roots: None,
        }
    }

    /// Refuses a raster whose header claims more samples than the limit allows.
    pub fn check(&self, cols: u64, rows: u64) -> Result<(), ReadError> {
        match cols.checked_mul(rows) {
            Some(n)
                if n.checked_mul(SAMPLE_BYTES)
                    .is_some_and(|b| b <= self.max_bytes)
                    && usize::try_from(n).is_ok() =>
            {
                Ok(())
            }
            _ => Err(ReadError::TooLarge {
                cols,
                rows,
                limit_mb: self.max_bytes >> 20,
            }),
        }
    }

    /// Refuses a header that declares more samples than the data in the file can fill:
    /// `fillable` samples at most, whatever the codec does. This is what keeps a few hundred
    /// bytes from claiming gigabytes.
    pub fn check_fillable(&self, cols: u64, rows: u64, fillable: u64) -> Result<(), ReadError> {
        // A small raster costs nothing to allocate, whatever its file holds.
        const FREE: u64 = 1 << 18;
        let n = cols.saturating_mul(rows);
        if n > fillable.max(FREE) {
            return Err(ReadError::Invalid {
                what: format!(
                    "the header declares {cols} x {rows} samples, but the image data in the file can fill at most {fillable} of them"
                ),
            });
        }
        Ok(())
    }
}

/// A file format reader.
pub trait RasterReader {
    /// True if this reader recognises the file (by extension and/or magic bytes).
    fn accepts(&self, path: &Path, head: &[u8]) -> bool;
    /// Reads the raster from `src`, an open file read from its start.
    fn read(&self, src: &mut Source, limits: &ReadLimits) -> Result<Raster, ReadError>;
}

/// A file opened once and read once, front to back, hashing every byte it gives out: the
/// content id it reports describes exactly the bytes a reader parsed from it, even should the
/// file be rewritten while it is read. Its first bytes are read at the open, for the readers
/// to recognise the format by.
pub struct Source {
    path: PathBuf,
    file: File,
    len: u64,
    head: Vec<u8>,
    /// How much of `head` has been given out.
    given: usize,
    hasher: blake3::Hasher,
}

/// Bytes read at the open for [`RasterReader::accepts`].
const HEAD_BYTES: u64 = 512;

impl Source {
    /// Opens `path` as [`open_untrusted`] does, within `limits.roots`, refusing what is not a
    /// non-empty regular file.
    pub fn open(path: &Path, limits: &ReadLimits) -> Result<Source, ReadError> {
        let mut file = open_regular_file(path, limits)?;
        let len = file.metadata()?.len();
        let mut head = Vec::with_capacity(HEAD_BYTES as usize);
        file.by_ref().take(HEAD_BYTES).read_to_end(&mut head)?;
        let mut hasher = blake3::Hasher::new();
        hasher.update(&head);
        Ok(Source {
            path: path.to_path_buf(),
            file,
            len,
            head,
            given: 0,
            hasher,
        })
    }

    /// The path it was opened by, for messages and the files beside it.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file's length when it was opened.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether the file was empty when it was opened (never, for one [`Source::open`] took).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The first bytes of the file (up to 512).
    pub fn head(&self) -> &[u8] {
        &self.head
    }

    /// The content id of the file as read: the rest that no reader took is read too, so the
    /// id is of the whole file, hex BLAKE3 as [`content_id`] computes it.
    pub fn content_id(mut self) -> std::io::Result<String> {
        std::io::copy(&mut self, &mut std::io::sink())?;
        Ok(self.hasher.finalize().to_hex().to_string())
    }
}

impl Read for Source {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.given < self.head.len() {
            let n = buf.len().min(self.head.len() - self.given);
            buf[..n].copy_from_slice(&self.head[self.given..self.given + n]);
            self.given += n;
            return Ok(n);
        }
        let n = self.file.read(buf)?;
        self.hasher.update(&buf[..n]);
        Ok(n)
    }
}

/// All readers, most specific first: magic bytes beat extensions.
pub fn readers() -> [&'static dyn RasterReader; 3] {
    [&GeoTiffReader, &HgtReader, &AsciiGridReader]
}

/// Reads any supported raster file, choosing the reader from magic bytes and extension.
pub fn read_raster(path: &Path, limits: &ReadLimits) -> Result<Raster, ReadError> {
    read_raster_hashed(path, limits).map(|(r, _)| r)
}

/// [`read_raster`], with the content id of the very bytes the raster was read from: the file
/// is opened and read once, so a file rewritten meanwhile cannot make the id describe other
/// bytes than those parsed.
pub fn read_raster_hashed(path: &Path, limits: &ReadLimits) -> Result<(Raster, String), ReadError> {
    let mut src = Source::open(path, limits)?;
    let raster = match readers().into_iter().find(|r| r.accepts(path, src.head())) {
        Some(reader) => reader.read(&mut src, limits)?,
        None => {
            return Err(ReadError::unsupported(format!(
                "{} is not a recognised elevation format (expected GeoTIFF .tif/.tiff, SRTM .hgt \
                 or ESRI ASCII grid .asc)",
                path.display()
            )))
        }
    };
    Ok((raster, src.content_id()?))
}

/// Why a file someone else controls was not opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The path names a directory.
    #[error("{} is a directory", .0.display())]
    Directory(PathBuf),
    /// The path names something other than a regular file (a device, a socket, a pipe).
    #[error("{} is not a regular file", .0.display())]
    NotAFile(PathBuf),
    /// The path does not resolve inside the folders it may be read from.
    #[error("{}", REFUSED_PATH)]
    Outside,
    /// Opening or reading the file failed.
    #[error("cannot read {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

impl OpenError {
    /// Whether nothing is there.
    pub fn is_not_found(&self) -> bool {
        matches!(self, OpenError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound)
    }
}

/// Opens a file that someone else may control. It is opened without blocking (a FIFO would
/// otherwise wait forever for a writer) and must be a regular file. With `roots`, the file
/// opened must be the one its path resolves to, symlinks followed, inside one of them: the
/// check is made on the open handle, so a symlink swapped between a check and the open
/// cannot lead outside.
pub fn open_untrusted(path: &Path, roots: Option<&[PathBuf]>) -> Result<File, OpenError> {
    use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
    let io = |source: std::io::Error| OpenError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path);
    let file = match (file, roots) {
        (Ok(f), _) => f,
        // Where a path leads outside, even whether it leads anywhere is not told.
        (Err(_), Some(_)) => return Err(OpenError::Outside),
        (Err(e), None) => return Err(io(e)),
    };
    let meta = file.metadata().map_err(io)?;
    if let Some(roots) = roots {
        let real = path.canonicalize().map_err(|_| OpenError::Outside)?;
        let same =
            std::fs::metadata(&real).is_ok_and(|m| (m.dev(), m.ino()) == (meta.dev(), meta.ino()));
        if !same || !roots.iter().any(|r| real.starts_with(r)) {
            return Err(OpenError::Outside);
        }
    }
    if meta.is_dir() {
        return Err(OpenError::Directory(path.to_path_buf()));
    }
    if !meta.is_file() {
        return Err(OpenError::NotAFile(path.to_path_buf()));
    }
    Ok(file)
}

/// Hex BLAKE3 of a file's bytes: the content id of a survey's source.
pub fn content_id(mut file: &File) -> std::io::Result<String> {
    let mut h = blake3::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(h.finalize().to_hex().to_string())
}

/// The content id of the file at `path`, opened as [`open_untrusted`] does.
pub fn file_content_id(path: &Path, roots: Option<&[PathBuf]>) -> Result<String, OpenError> {
    let file = open_untrusted(path, roots)?;
    content_id(&file).map_err(|source| OpenError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Opens a raster file where `limits` allow, refusing directories, special files and empty
/// files with a clear message rather than the OS's terse one (or a confusing decoder error on
/// zero bytes).
pub(crate) fn open_regular_file(path: &Path, limits: &ReadLimits) -> Result<File, ReadError> {
    let file = open_untrusted(path, limits.roots.as_deref()).map_err(|e| match e {
        OpenError::Outside => ReadError::Outside,
        OpenError::Directory(p) => {
            ReadError::invalid(format!("{} is a directory, not a raster file", p.display()))
        }
        OpenError::NotAFile(p) => {
            ReadError::invalid(format!("{} is not a regular file", p.display()))
        }
        OpenError::Io { source, .. } => source.into(),
    })?;
    if file.metadata()?.len() == 0 {
        return Err(ReadError::invalid(format!(
            "{} is empty (0 bytes)",
            path.display()
        )));
    }
    Ok(file)
}

pub(crate) fn has_extension(path: &Path, wanted: &[&str]) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| wanted.iter().any(|w| e.eq_ignore_ascii_case(w)))
}

#[cfg(test)]
pub(crate) mod test_support {
    use std::path::PathBuf;

    /// Crops of real surveys, committed with the tests (tests/data/real, and the README there
    /// for where each came from).
    pub fn data_file(name: &str) -> PathBuf {
        let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/data/real")
            .join(name);
        assert!(p.is_file(), "test file missing: {}", p.display());
        p
    }

    pub fn assert_close(a: f64, b: f64, tol: f64, what: &str) {
        assert!((a - b).abs() <= tol, "{what}: {a} != {b} (tolerance {tol})");
    }

    pub fn assert_gt_close(got: [f64; 6], want: [f64; 6], tol: f64) {
        for i in 0..6 {
            assert_close(
                got[i],
                want[i],
                tol,
                &format!("geotransform[{i}] of {got:?}"),
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_refuse_overflowing_and_large_headers() {
        let limits = ReadLimits::default();
        assert!(limits.check(32_768, 32_768).is_ok());
        assert!(limits.check(32_768, 32_769).is_err());
        let err = limits.check(1_000_000, 1_000_000).unwrap_err();
        assert!(matches!(err, ReadError::TooLarge { .. }));
        assert!(err.to_string().contains("1000000 x 1000000"), "{err}");
        assert!(limits.check(u64::MAX, 2).is_err());
        assert!(ReadLimits::mb(1).check(512, 512).is_ok());
        assert!(ReadLimits::mb(1).check(512, 513).is_err());
        // Data for a quarter of the samples cannot fill the whole raster.
        assert!(limits.check_fillable(2000, 2000, 1_000_000).is_err());
        assert!(limits.check_fillable(2000, 2000, 4_000_000).is_ok());
        assert!(
            limits.check_fillable(100, 100, 0).is_ok(),
            "small rasters are free"
        );
    }

    #[test]
    fn read_raster_refuses_unknown_directory_and_empty() {
        let dir = tempfile::tempdir().unwrap();
        let limits = ReadLimits::default();

        let unknown = dir.path().join("notes.txt");
        std::fs::write(&unknown, b"hello").unwrap();
        let err = read_raster(&unknown, &limits).unwrap_err();
        assert!(matches!(err, ReadError::Unsupported { .. }), "{err}");

        let sub = dir.path().join("x.tif");
        std::fs::create_dir(&sub).unwrap();
        let err = read_raster(&sub, &limits).unwrap_err();
        assert!(err.to_string().contains("is a directory"), "{err}");

        let empty = dir.path().join("empty.hgt");
        std::fs::write(&empty, b"").unwrap();
        let err = read_raster(&empty, &limits).unwrap_err();
        assert!(err.to_string().contains("empty"), "{err}");

        let missing = dir.path().join("missing.tif");
        let err = read_raster(&missing, &limits).unwrap_err();
        assert!(matches!(err, ReadError::Io(_)), "{err}");
    }

    #[test]
    fn read_raster_dispatches_on_real_files() {
        let limits = ReadLimits::default();
        let hgt = read_raster(&test_support::data_file("hgt/N44E005.hgt"), &limits).unwrap();
        assert_eq!((hgt.cols, hgt.rows), (1201, 1201));
        let tif = read_raster(
            &test_support::data_file("rhine_deflate_strips.tif"),
            &limits,
        )
        .unwrap();
        assert_eq!((tif.cols, tif.rows), (200, 150));
        let asc = read_raster(&test_support::data_file("ventoux.asc"), &limits).unwrap();
        assert_eq!((asc.cols, asc.rows), (120, 100));
    }
}
