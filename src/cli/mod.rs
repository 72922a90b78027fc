//! The command line: one module a job. [`client`] reaches the daemon (or opens the store
//! directly), [`serve`] runs the daemon, [`admin`] and [`terrain`] hold the commands of the two
//! services, and [`json`] the stable JSON they print.

mod admin;
mod client;
mod export;
mod json;
mod serve;
mod terrain;

use clap::{Args, Parser, Subcommand, ValueEnum};
use client::Target;
use patchwork::serve::proto as pb;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "patchwork",
    version,
    about = "A terrain database of overlapping DEM surveys"
)]
pub struct Cli {
    #[command(subcommand)]
    pub cmd: Cmd,
}

#[derive(Subcommand)]
pub enum Cmd {
    /// Run the daemon: watch the inbox and serve the gRPC API.
    Serve(ServeArgs),
    /// Print the configuration `serve` would run with, key by key, and where each value came
    /// from: the compiled-in default, the file, or the environment.
    Config(ConfigArgs),
    /// Ingest files now.
    Ingest(IngestArgs),
    /// List surveys, failed files included.
    Surveys(SurveysArgs),
    /// Wait until the daemon answers and each file named (a file dropped into the inbox, say)
    /// is a survey it serves; fail at once, with the reason, where one of them fails.
    Wait(WaitArgs),
    /// Retire a survey by id or source path. A survey whose file stays in the inbox stays
    /// retired until that file's content changes.
    Retire(RetireArgs),
    /// Remove the failure recorded for a file.
    Forget(ForgetArgs),
    /// Store statistics.
    Stats(StatsArgs),
    /// Re-check the store and the index.
    Verify(VerifyArgs),
    /// Drop damaged surveys for good, so that their files can be ingested again.
    Repair(RepairArgs),
    /// Remove retired surveys for good and give disk space back.
    Compact(CompactArgs),
    /// Patches for a region and error, or for a view.
    Query(QueryArgs),
    /// List the GPU adapters with compute shaders, one a line. The daemon runs this in a child
    /// process, so that drivers it will not use are never loaded into it.
    #[command(hide = true)]
    ProbeGpu,
    /// Resample a north-up tile and write it as GeoTIFF (.tif) or numpy (.npy).
    Tile(TileArgs),
    /// Heights at points, or along a line: what any tile holding them gives there.
    Sample(SampleArgs),
    /// Triangulate a uniform cut's surface and write it as OBJ (.obj), binary glTF (.glb) or
    /// Cesium quantized-mesh (.terrain; a geographic store only).
    Mesh(MeshArgs),
    /// Write the web pyramid's raster-DEM tiles as one file to host without a server:
    /// PMTiles or MBTiles, the same tiles the HTTP server serves.
    Export(export::ExportArgs),
    /// Print an nginx config that routes web tiles to replicas of regions
    /// (`serve --follow URL --region ...`) and the rest to a replica of the whole store.
    ProxyConfig(ProxyConfigArgs),
}

// The arguments of `patchwork proxy-config`.
#[derive(Args)]
pub struct ProxyConfigArgs {
    /// What nginx listens on: a port, or ADDRESS:PORT.
    #[arg(long, default_value = "8080")]
    pub listen: String,
    /// The HTTP server of a replica of the whole store (or the writer): http://HOST:PORT.
    #[arg(long, value_name = "URL")]
    pub whole: String,
    /// A replica of a region: NAME=http://HOST:PORT@WEST,SOUTH,EAST,NORTH, the box in degrees
    /// (its region, for a store in EPSG:4326). Repeat for each.
    #[arg(long, value_name = "NAME=URL@W,S,E,N", allow_hyphen_values = true)]
    pub replica: Vec<String>,
    /// The deepest tile level routed to a region.
    #[arg(long, default_value_t = 24)]
    pub max_level: u32,
}

// The arguments of `patchwork serve`.
#[derive(Args)]
pub struct ServeArgs {
    #[arg(long, env = "PATCHWORK_CONFIG", value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Serve as a read replica of the store at URL (s3://bucket/prefix, or file:///folder),
    /// following its writer's commits; `data_dir` is the replica's own, empty at first.
    #[arg(long, value_name = "URL")]
    pub follow: Option<String>,
    /// With --follow: hold and answer only the region XMIN,YMIN,XMAX,YMAX of the store's CRS
    /// (the surveys that reach it), refusing requests beyond it.
    #[arg(
        long,
        value_name = "XMIN,YMIN,XMAX,YMAX",
        requires = "follow",
        allow_hyphen_values = true
    )]
    pub region: Option<String>,
}

// The arguments of `patchwork config`.
#[derive(Args)]
pub struct ConfigArgs {
    #[arg(long, env = "PATCHWORK_CONFIG", value_name = "FILE")]
    pub config: Option<PathBuf>,
}

// The arguments of `patchwork ingest`.
#[derive(Args)]
pub struct IngestArgs {
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Accuracy ε in metres for files without a sidecar.
    #[arg(long, value_name = "M")]
    pub accuracy: Option<f64>,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork surveys`.
#[derive(Args)]
pub struct SurveysArgs {
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork wait`.
#[derive(Args)]
pub struct WaitArgs {
    pub files: Vec<PathBuf>,
    /// Give up after this many seconds.
    #[arg(long, value_name = "S", default_value_t = 120.0)]
    pub timeout: f64,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork retire`.
#[derive(Args)]
pub struct RetireArgs {
    pub id_or_source: String,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork forget`.
#[derive(Args)]
pub struct ForgetArgs {
    pub path: PathBuf,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork stats`.
#[derive(Args)]
pub struct StatsArgs {
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork verify`.
#[derive(Args)]
pub struct VerifyArgs {
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork repair`.
#[derive(Args)]
pub struct RepairArgs {
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork compact`.
#[derive(Args)]
pub struct CompactArgs {
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork query`.
#[derive(Args)]
pub struct QueryArgs {
    #[command(flatten)]
    pub cut: CutArgs,
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork tile`.
#[derive(Args)]
pub struct TileArgs {
    #[arg(long, value_name = "XMIN,YMIN,XMAX,YMAX", allow_hyphen_values = true)]
    pub roi: String,
    #[arg(long, value_name = "WxH")]
    pub size: String,
    #[arg(long, value_name = "E", default_value_t = 0.0)]
    pub error: f64,
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    pub backend: BackendArg,
    /// The tile's CRS (an EPSG code such as EPSG:3857, a WKT or a PROJ string): --roi is
    /// in it, and so are the tile's samples and its GeoTIFF. The store's by default.
    #[arg(long, value_name = "CRS")]
    pub crs: Option<String>,
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// What the heights are measured from: store (the store's vertical CRS), ellipsoid
    /// (WGS 84's, as GPS and Cesium take them) or a vertical CRS as EPSG:n.
    #[arg(long, value_name = "FRAME", default_value = "store")]
    pub heights: String,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork sample`.
#[derive(Args)]
pub struct SampleArgs {
    /// Points as X,Y pairs: X1,Y1,X2,Y2,...
    #[arg(long, value_name = "X,Y,...", allow_hyphen_values = true)]
    pub points: Option<String>,
    /// A line from X0,Y0 to X1,Y1, sampled at --count evenly spaced points.
    #[arg(long, value_name = "X0,Y0,X1,Y1", allow_hyphen_values = true)]
    pub line: Option<String>,
    #[arg(long, value_name = "N", default_value_t = 100)]
    pub count: usize,
    #[arg(long, value_name = "E", default_value_t = 0.0)]
    pub error: f64,
    /// The points' CRS; the store's by default.
    #[arg(long, value_name = "CRS")]
    pub crs: Option<String>,
    #[arg(long)]
    pub json: bool,
    /// What the heights are measured from: store (the store's vertical CRS), ellipsoid
    /// (WGS 84's, as GPS and Cesium take them) or a vertical CRS as EPSG:n.
    #[arg(long, value_name = "FRAME", default_value = "store")]
    pub heights: String,
    /// Say what served each height: the survey, its file, level, cell and error.
    #[arg(long)]
    pub sources: bool,
    #[command(flatten)]
    pub target: Target,
}

// The arguments of `patchwork mesh`.
#[derive(Args)]
pub struct MeshArgs {
    #[arg(long, value_name = "XMIN,YMIN,XMAX,YMAX", allow_hyphen_values = true)]
    pub roi: String,
    /// The cut's error, metres.
    #[arg(long, value_name = "E", default_value_t = 0.0)]
    pub error: f64,
    /// How far the triangles may depart from the resampled heights, metres.
    #[arg(long, value_name = "M", default_value_t = 1.0)]
    pub mesh_error: f64,
    /// Grid vertices a row; 2^n + 1 wastes nothing, any other size is padded inside.
    #[arg(long, value_name = "N", default_value_t = 257)]
    pub size: u32,
    /// Grid rows (default: as many as --size).
    #[arg(long, value_name = "N")]
    pub rows: Option<u32>,
    /// How far the surface may be drawn over a void from the nearest measured vertex,
    /// metres: holes narrower than twice this close, wider ones shrink by this much at
    /// most (0: holes kept exact).
    #[arg(long, value_name = "M", default_value_t = 0.0)]
    pub hole_reach: f64,
    /// Depth of the skirts under the tile's border, metres (0: none). Quantized-mesh
    /// leaves them out: Cesium makes its own from the edge vertices.
    #[arg(long, value_name = "M", default_value_t = 0.0)]
    pub skirt: f64,
    #[arg(long, value_enum, default_value_t = BorderArg::Shared)]
    pub border: BorderArg,
    #[arg(long, value_enum, default_value_t = MethodArg::Rtin)]
    pub method: MethodArg,
    /// Where the cut is resampled.
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    pub backend: BackendArg,
    /// The CRS of --roi and of the vertices (an EPSG code, a WKT or a PROJ string); the
    /// store's by default.
    #[arg(long, value_name = "CRS")]
    pub crs: Option<String>,
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// What the heights are measured from: store (the store's vertical CRS), ellipsoid
    /// (WGS 84's, as GPS and Cesium take them) or a vertical CRS as EPSG:n.
    #[arg(long, value_name = "FRAME", default_value = "store")]
    pub heights: String,
    #[command(flatten)]
    pub target: Target,
}

/// Where a tile is resampled.
#[derive(Clone, Copy, ValueEnum)]
pub enum BackendArg {
    /// The GPU when there is one, else the CPU.
    Auto,
    Cpu,
    Gpu,
}

impl From<BackendArg> for pb::Backend {
    fn from(b: BackendArg) -> Self {
        match b {
            BackendArg::Auto => pb::Backend::Auto,
            BackendArg::Cpu => pb::Backend::Cpu,
            BackendArg::Gpu => pb::Backend::Gpu,
        }
    }
}

/// How a mesh is triangulated.
#[derive(Clone, Copy, ValueEnum)]
pub enum MethodArg {
    /// A triangle bintree: the fewest triangles.
    Rtin,
    /// A restricted quadtree of fans, midpoints omitted where a coarser node meets.
    Quadtree,
}

impl From<MethodArg> for pb::MeshMethod {
    fn from(m: MethodArg) -> Self {
        match m {
            MethodArg::Rtin => pb::MeshMethod::Rtin,
            MethodArg::Quadtree => pb::MeshMethod::Quadtree,
        }
    }
}

/// What a mesh keeps on the tile's border.
#[derive(Clone, Copy, ValueEnum)]
pub enum BorderArg {
    /// Every border vertex, so that tiles of one error fit without cracks.
    Shared,
    /// Simplified like the inside: fewer triangles, cracks hidden only by skirts.
    Adaptive,
}

impl From<BorderArg> for pb::MeshBorder {
    fn from(b: BorderArg) -> Self {
        match b {
            BorderArg::Shared => pb::MeshBorder::Shared,
            BorderArg::Adaptive => pb::MeshBorder::Adaptive,
        }
    }
}

#[derive(Args, Clone)]
pub struct CutArgs {
    #[arg(long, value_name = "XMIN,YMIN,XMAX,YMAX", allow_hyphen_values = true)]
    pub roi: Option<String>,
    #[arg(long, value_name = "E")]
    pub error: Option<f64>,
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    pub eye: Option<String>,
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    pub look: Option<String>,
    #[arg(long, value_name = "DEG", default_value_t = 60.0)]
    pub fov: f64,
    #[arg(long, value_name = "PX", default_value_t = 1024)]
    pub viewport: u32,
    #[arg(long, value_name = "P", default_value_t = 1.0)]
    pub pixel_error: f64,
    /// The CRS of --roi (an EPSG code, a WKT or a PROJ string); the store's by default.
    #[arg(long, value_name = "CRS")]
    pub crs: Option<String>,
}

pub type Fail = Box<dyn std::error::Error>;

pub fn numbers<const N: usize>(s: &str, what: &str) -> Result<[f64; N], Fail> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("{what}: expected {N} comma-separated numbers, got {s:?}"))?;
    v.try_into()
        .map_err(|_| format!("{what}: expected {N} comma-separated numbers, got {s:?}").into())
}

pub fn rect(s: &str) -> Result<pb::Rect, Fail> {
    let [xmin, ymin, xmax, ymax] = numbers::<4>(s, "--roi")?;
    Ok(pb::Rect {
        xmin,
        ymin,
        xmax,
        ymax,
    })
}

/// A path for a line of output: control characters (a newline in a file name, say) escaped,
/// so that one name stays one line.
pub fn printable(s: &str) -> std::borrow::Cow<'_, str> {
    if s.chars().any(char::is_control) {
        s.escape_debug().to_string().into()
    } else {
        s.into()
    }
}

/// What a tile or mesh achieved against the error `e` asked: its largest patch error, or
/// where no data is as accurate as `e`, how much of it and what served there.
pub fn achieved(e: f64, max_error: f64, short: Option<&pb::Shortfall>, what: &str) -> String {
    match short {
        Some(s) => format!(
            "no data as accurate as {e} m over {:.0}% of the {what}: served the most accurate there, errors {:.1}–{:.1} m",
            100.0 * s.share,
            s.min_error_m,
            s.max_error_m
        ),
        None => format!("max error {max_error:.3} m"),
    }
}

/// Prints the nginx config of `patchwork proxy-config`.
fn proxy_config(a: ProxyConfigArgs) -> Result<(), Fail> {
    use patchwork::serve::web::proxy;
    let whole = proxy::upstream_addr(&a.whole).map_err(|e| format!("--whole {e}"))?;
    let regions = a
        .replica
        .iter()
        .map(|r| proxy::RegionRoute::parse(r))
        .collect::<Result<Vec<_>, _>>()?;
    print!("{}", proxy::nginx(&a.listen, &whole, &regions, a.max_level));
    Ok(())
}

/// Runs one command.
pub async fn run(cli: Cli) -> Result<(), Fail> {
    match cli.cmd {
        Cmd::Serve(a) => serve::serve(a.config, a.follow, a.region).await,
        Cmd::ProbeGpu => serve::probe_gpu(),
        Cmd::Config(a) => serve::print_config(a.config.as_deref()),
        Cmd::Ingest(a) => admin::ingest(a).await,
        Cmd::Surveys(a) => admin::surveys(a).await,
        Cmd::Wait(a) => admin::wait(a).await,
        Cmd::Retire(a) => admin::retire(a).await,
        Cmd::Forget(a) => admin::forget(a).await,
        Cmd::Stats(a) => admin::stats(a).await,
        Cmd::Verify(a) => admin::verify(a).await,
        Cmd::Repair(a) => admin::repair(a).await,
        Cmd::Compact(a) => admin::compact(a).await,
        Cmd::Query(a) => terrain::query(a).await,
        Cmd::Tile(a) => terrain::tile(a).await,
        Cmd::Sample(a) => terrain::sample(a).await,
        Cmd::Mesh(a) => terrain::mesh(a).await,
        Cmd::Export(a) => export::export(a).await,
        Cmd::ProxyConfig(a) => proxy_config(a),
    }
}
