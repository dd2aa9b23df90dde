//! The `qemd` command line: argument definitions and their conversion to library parameters.
//!
//! Parsing (clap) and validation are kept apart, as in ripgrep: the denoising flags are the
//! parameter spec's [`SpecOverlay`] (flattened into [`DenoiseArgs`]), resolved and validated by
//! [`SpecOverlay::resolve`] like every other request, and `main` only dispatches.

use std::path::{Path, PathBuf};

use clap::{Args, Parser, Subcommand, ValueEnum};

use crate::eval::lidar::{Frame, SensorFlags, SensorKind};
use crate::io::Format;
use crate::io::raw::BinLayout;
use crate::pipeline::SpecOverlay;

/// Feature-preserving denoising of meshes and point clouds with the Quadric Error Metric.
#[derive(Debug, Parser)]
#[command(name = "qemd", version, about, long_about = None)]
pub struct Cli {
    /// The command to run.
    #[command(subcommand)]
    pub command: Command,
}

/// `qemd` subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Denoise a mesh or point cloud (format from the extension).
    Denoise(Box<DenoiseArgs>),
    /// Describe a file: format, point count, schema and extra fields, bounds, CRS, scale and
    /// offset, point spacing, classes present (as `pdal info` and `lasinfo`).
    Info(InfoArgs),
    /// Generate a synthetic shape (mesh, or point samples with --points), or with `synth lidar` a
    /// simulated LiDAR scan of a street with exact truth.
    Synth(SynthArgs),
    /// Score a denoised simulated scan against its truth (`qemd synth lidar --truth`), per class.
    Score(ScoreArgs),
    /// Add seeded noise to a mesh or point cloud.
    Noise(NoiseArgs),
    /// The real-scan protocol: displacement over each point's 16-NN radius (do no harm), or with
    /// --clean the noise removed, per class.
    Harm(HarmArgs),
    /// Compare a denoised file with the clean one (the metrics of docs/EVALUATION.md).
    Eval(EvalArgs),
    /// Run the paper's Table I protocol (20/40/80 % iso noise) on a clean mesh.
    Table(TableArgs),
    /// Render a mesh or point cloud to PNG with the software renderer.
    Render(RenderArgs),
    /// Generate a noisy scan, denoise it, print the metrics and write files and renderings.
    Demo(DemoArgs),
    /// Write the quality report (Table I for four methods, charts, renderings, benchmark pairs,
    /// frequency response) as HTML and Markdown.
    Report(ReportArgs),
    /// The paper's frequency-response analysis on a noisy height-field patch: chart, CSV, summary.
    Spectrum(SpectrumArgs),
    /// Run the HTTP job service (uploads, asynchronous jobs, synchronous denoise).
    Serve(ServeArgs),
    /// Scale-out: plan a tiled job into a work directory and print each phase's task count.
    Plan(Box<PlanArgs>),
    /// Scale-out: run one task of one phase of a planned job (the index from the flags or the
    /// engine: SLURM, Kubernetes Indexed Job, AWS Batch).
    Worker(WorkerArgs),
    /// Scale-out: write a planned job's output (running the stitch if it has not run).
    Finish(FinishArgs),
    /// Scale-out: each phase's progress, from the committed files of the work directory.
    Status(StatusArgs),
    /// Scale-out: Kubernetes manifests for a planned job, one Indexed Job per phase (apply them
    /// in order, each after the previous one completed).
    K8s(K8sArgs),
}

/// Flags of `qemd plan`: the input and the denoising flags of `qemd denoise`, frozen in the work
/// directory so workers need none.
#[derive(Debug, Args)]
pub struct PlanArgs {
    /// Input file (not a stream): on a file system every task can read, or anywhere for an S3
    /// work directory, which receives a copy.
    pub input: PathBuf,
    /// The work directory: a path or file:///abs/path on a file system every task can reach, or
    /// s3://bucket/prefix (endpoint and credentials from the AWS_* environment).
    #[arg(long)]
    pub work: String,
    /// The format, denoising, thread and memory flags (as `qemd denoise`; the output format is
    /// the stitch's, by default the input's, and `qemd finish` may still write another).
    #[command(flatten)]
    pub run: RunFlags,
    /// Print the task counts as JSON.
    #[arg(long)]
    pub json: bool,
    /// Print nothing but errors (and the JSON, with --json).
    #[arg(short, long)]
    pub quiet: bool,
}

impl PlanArgs {
    /// The input and output formats these flags select (`None`: from the extension or content,
    /// and the input's for the output).
    pub fn formats(&self) -> (Option<Format>, Option<Format>) {
        self.run.formats(&self.input, None)
    }
}

/// Flags of `qemd worker`.
#[derive(Debug, Args)]
pub struct WorkerArgs {
    /// The work directory of a planned job.
    #[arg(long)]
    pub work: String,
    /// The phase.
    #[arg(long, value_enum)]
    pub phase: crate::pipeline::scaleout::Phase,
    /// This task's index, 0-based (default: SLURM_ARRAY_TASK_ID, JOB_COMPLETION_INDEX or
    /// AWS_BATCH_JOB_ARRAY_INDEX; else 0).
    #[arg(long)]
    pub index: Option<u64>,
    /// Tasks sharing the phase (default: SLURM_ARRAY_TASK_COUNT, else the phase's task count
    /// from the plan; 1 without an index).
    #[arg(long)]
    pub of: Option<u64>,
    /// Worker threads (default: all cores); the output is identical for any value.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Print what the task did as JSON.
    #[arg(long)]
    pub json: bool,
    /// Print nothing but errors.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Flags of `qemd finish`.
#[derive(Debug, Args)]
pub struct FinishArgs {
    /// The work directory of a planned job.
    #[arg(long)]
    pub work: String,
    /// Output file, or - for standard output.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Output format, overriding the extension.
    #[arg(long, visible_alias = "output-format", ignore_case = true, value_parser = format_parser())]
    pub format: Option<Format>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Print nothing but errors.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Flags of `qemd status`.
#[derive(Debug, Args)]
pub struct StatusArgs {
    /// The work directory of a planned job.
    #[arg(long)]
    pub work: String,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// Flags of `qemd k8s`; the defaults are [`crate::k8s`]'s.
#[derive(Debug, Args)]
pub struct K8sArgs {
    /// The work directory of a planned job (s3://bucket/prefix).
    #[arg(long)]
    pub work: String,
    /// Write one file per phase into this directory (1-partition.yaml …); default: every
    /// manifest to standard output as one YAML stream.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Prefix of the Job names (`NAME-partition` …) [default: qemd- and a hash of the URL].
    #[arg(long)]
    pub name: Option<String>,
    /// Namespace of the Jobs [default: unset, kubectl's current one].
    #[arg(long)]
    pub namespace: Option<String>,
    /// Container image whose entrypoint is qemd (docker/Dockerfile).
    #[arg(long, default_value = crate::k8s::DEFAULT_IMAGE)]
    pub image: String,
    /// Secret whose keys become the pods' environment (AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY,
    /// AWS_REGION, AWS_ENDPOINT_URL …).
    #[arg(long, default_value = crate::k8s::DEFAULT_SECRET)]
    pub secret: String,
    /// Pods of one phase at a time (capped at the phase's task count).
    #[arg(long, default_value_t = crate::k8s::DEFAULT_PARALLELISM)]
    pub parallelism: u32,
    /// Retries of one index before its Job fails.
    #[arg(long, default_value_t = crate::k8s::DEFAULT_BACKOFF_PER_INDEX)]
    pub backoff_per_index: u32,
    /// Cores per pod: its CPU request and the worker's --threads.
    #[arg(long, default_value_t = crate::k8s::DEFAULT_CPUS)]
    pub cpus: u32,
}

impl K8sArgs {
    /// The manifest options these flags give.
    pub fn options(&self) -> crate::k8s::K8sOptions {
        crate::k8s::K8sOptions {
            name: self.name.clone(),
            namespace: self.namespace.clone(),
            image: self.image.clone(),
            secret: self.secret.clone(),
            parallelism: self.parallelism,
            backoff_per_index: self.backoff_per_index,
            cpus: self.cpus,
        }
    }
}

/// Flags of `qemd serve`; everything else comes from the configuration.
#[derive(Debug, Args)]
pub struct ServeArgs {
    /// Configuration file (overrides config/default.toml; QEMD_* variables override it).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Address to listen on, host:port (overrides `listen`; port 0 picks a free one).
    #[arg(long)]
    pub listen: Option<String>,
    /// Data directory (overrides `data_dir`).
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
}

/// Flags of `qemd denoise`.
#[derive(Debug, Args)]
pub struct DenoiseArgs {
    /// Input file (.ply, .obj, .off, .las, .laz, .copc.laz, .e57, .pcd, .xyz, .txt, .pts, .bin,
    /// .pcd.bin), or - for standard input (spooled to --temp-dir; the format is told from the
    /// content unless --input-format is given).
    pub input: PathBuf,
    /// Output file, or - for standard output; its extension picks the format unless --format is
    /// given (standard output and other streams default to the input's format). Regular files
    /// are replaced atomically; devices, FIFOs and standard output are written directly (LAS/LAZ
    /// needs to seek: towards a stream it is spooled to --temp-dir, then copied).
    #[arg(short, long)]
    pub output: PathBuf,
    /// The format, denoising, thread and memory flags (shared with `qemd plan`).
    #[command(flatten)]
    pub run: RunFlags,
    /// Directory for spill files and the spool of standard input; must exist (default:
    /// `temp_dir` of the configuration, else the system temporary directory). A tiled run needs
    /// about 88 bytes per point free there (112 with --write-normals; checked before it starts).
    #[arg(long)]
    pub temp_dir: Option<PathBuf>,
    /// Write a JSON report (counts, tiles, per-phase wall and CPU time, peak RSS) here.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Point clouds: the sensor's trajectory, a text file of `gps_time x y z` lines in the
    /// points' time base and coordinates (mobile mapping, airborne): each return's beam runs from
    /// the position at its GPS time, and the default operator moves it only along that beam.
    /// The cloud must fit --memory-budget (a tiled run does not carry the times yet).
    #[arg(long, value_name = "FILE", conflicts_with = "sensor_origin")]
    pub trajectory: Option<PathBuf>,
    /// Print nothing but errors.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Parses a `--format` value.
pub fn parse_format(s: &str) -> Result<Format, String> {
    Format::from_name(s).ok_or_else(|| format!("unknown format `{s}`"))
}

/// The `--format` parser: lists [`Format::NAMES`] in the help and maps a name to its format.
fn format_parser() -> impl clap::builder::TypedValueParser<Value = Format> {
    use clap::builder::TypedValueParser as _;
    clap::builder::PossibleValuesParser::new(Format::NAMES)
        .map(|s| Format::from_name(&s).expect("every listed name parses"))
}

/// The format of one side of a run given `--bin-fields`: a raw format (given, told by the
/// extension, or untold, as for standard input) takes the layout; any other stays.
fn with_layout(given: Option<Format>, path: &Path, layout: Option<BinLayout>) -> Option<Format> {
    let Some(layout) = layout else {
        return given;
    };
    let raw = match given {
        Some(f) => f.bin_layout().is_some(),
        None => Format::from_path(path).map_or(true, |f| f.bin_layout().is_some()),
    };
    if raw {
        Some(Format::Bin(layout))
    } else {
        given
    }
}

impl DenoiseArgs {
    /// The input and output formats these flags select (`None`: from the extension or content).
    pub fn formats(&self) -> (Option<Format>, Option<Format>) {
        self.run.formats(&self.input, Some(&self.output))
    }
}

/// The flags `qemd denoise` and `qemd plan` share: formats, the denoising parameters, threads,
/// memory and tiling (one definition, so the two commands cannot drift apart).
#[derive(Debug, Args)]
pub struct RunFlags {
    /// Output format, overriding the extension.
    #[arg(long, visible_alias = "output-format", ignore_case = true, value_parser = format_parser())]
    pub format: Option<Format>,
    /// Input format, overriding the extension and the content.
    #[arg(long, ignore_case = true, value_parser = format_parser())]
    pub input_format: Option<Format>,
    /// Layout of raw little-endian float32 .bin records, input and output: comma-separated x, y,
    /// z, intensity (i), ring, time (t) and _ (unnamed), or a count N (x, y, z and N − 3
    /// unnamed). Default: KITTI x,y,z,i for *.bin, nuScenes x,y,z,i,ring for *.pcd.bin.
    #[arg(long, value_name = "FIELDS|N", value_parser = BinLayout::parse)]
    pub bin_fields: Option<BinLayout>,
    /// The denoising parameters (the same spec as a job's `params` and the sync query string).
    #[command(flatten)]
    pub spec: SpecOverlay,
    /// Worker threads (default: all cores); the output is identical for any value.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Memory budget; clouds whose working set is larger run in tiles (e.g. "4 GiB"), and it
    /// sizes the tiles. Default: `memory_budget` of the configuration, 1 GiB unless set there or
    /// in QEMD_MEMORY_BUDGET.
    #[arg(long)]
    pub memory_budget: Option<bytesize::ByteSize>,
    /// Force tiling with about this many points per tile (default: tiles only for clouds over
    /// the memory budget, sized to it).
    #[arg(long)]
    pub tile_points: Option<u64>,
    /// Input records per partition part of a tiled run: parts are read side by side, and each is
    /// a task of `qemd worker --phase partition` (default 2000000, at most 4096 spill files;
    /// LAS, LAZ with fixed-size chunks, binary PLY and PCD, raw .bin; other formats use one
    /// part). Only the speed depends on it.
    #[arg(long)]
    pub part_points: Option<u64>,
    /// Configuration file (overrides config/default.toml; QEMD_* variables override it).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

impl RunFlags {
    /// The formats of `input` and of `output` (`None` for the output: the input's, unless
    /// `--format` is given).
    fn formats(&self, input: &Path, output: Option<&Path>) -> (Option<Format>, Option<Format>) {
        let output = match (output, self.format) {
            (Some(path), given) => with_layout(given, path, self.bin_fields),
            (None, Some(f)) => with_layout(Some(f), Path::new(""), self.bin_fields),
            (None, None) => None,
        };
        (
            with_layout(self.input_format, input, self.bin_fields),
            output,
        )
    }
}

/// Flags of `qemd info`.
#[derive(Debug, Args)]
pub struct InfoArgs {
    /// The file (any format `qemd denoise` reads), or - for standard input.
    pub input: PathBuf,
    /// Input format, overriding the extension and the content.
    #[arg(long, ignore_case = true, value_parser = format_parser())]
    pub input_format: Option<Format>,
    /// Layout of raw little-endian float32 .bin records (as `qemd denoise --bin-fields`).
    #[arg(long, value_name = "FIELDS|N", value_parser = BinLayout::parse)]
    pub bin_fields: Option<BinLayout>,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

impl InfoArgs {
    /// The input format these flags select (`None`: from the extension or content).
    pub fn format(&self) -> Option<Format> {
        with_layout(self.input_format, &self.input, self.bin_fields)
    }
}

/// Flags of `qemd synth`.
#[derive(Debug, Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct SynthArgs {
    /// `lidar`: a simulated scan instead of a shape.
    #[command(subcommand)]
    pub command: Option<SynthCommand>,
    /// sphere, cube, csg, torus or step.
    #[arg(required = true)]
    pub shape: Option<String>,
    /// Output file.
    #[arg(short, long, required = true)]
    pub output: Option<PathBuf>,
    /// Mesh resolution (subdivision level for the sphere, cells per edge otherwise).
    #[arg(long)]
    pub resolution: Option<usize>,
    /// Write this many surface samples (a point cloud) instead of the mesh.
    #[arg(long)]
    pub points: Option<u64>,
    /// Seed of the point sampler.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// `qemd synth` subcommands.
#[derive(Debug, Subcommand)]
pub enum SynthCommand {
    /// Simulate a LiDAR scan of a parametric street with exact truth: the noisy scan (-o), the
    /// same returns without noise (--clean), the truth (--truth) and the trajectory.
    Lidar(Box<LidarArgs>),
}

/// Flags of `qemd synth lidar`; the sensor's defaults are in `eval::lidar::sensors`.
#[derive(Debug, Args)]
pub struct LidarArgs {
    /// The noisy scan: .las, .laz, .ply, .xyz, .pcd, .bin (KITTI) or .pcd.bin (nuScenes).
    #[arg(short, long)]
    pub output: PathBuf,
    /// The sensor.
    #[arg(long, value_enum, default_value_t = SensorKind::Spinning)]
    pub sensor: SensorKind,
    /// Seed of the noise, jitter and dropouts (and of the scene, unless --scene-seed).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Seed of the scene [default: --seed].
    #[arg(long)]
    pub scene_seed: Option<u64>,
    /// Write the same returns without range noise and angular jitter here (any scan format).
    #[arg(long)]
    pub clean: Option<PathBuf>,
    /// Write the truth here (PLY: the scene mesh and each return's noise-free position).
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Write the sensor's position over time here (text: gps_time x y z per line).
    #[arg(long)]
    pub trajectory_out: Option<PathBuf>,
    /// Frame of every file [default: sensor for a sweep written as .pcd, .bin or .pcd.bin,
    /// street otherwise].
    #[arg(long, value_enum)]
    pub frame: Option<Frame>,
    /// The scene (only `street` so far).
    #[arg(long, default_value = "street", value_parser = ["street"])]
    pub scene: String,
    /// Length of the street (m).
    #[arg(long, default_value_t = crate::eval::lidar::street::DEFAULT_LENGTH)]
    pub length: f64,
    /// The sculpted object on a sidewalk: torus, sphere, cube, csg or none.
    #[arg(long, default_value = "torus")]
    pub object: String,
    /// A mesh file (PLY, OBJ, OFF) placed into the scene as an `object`.
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Where the bottom centre of the mesh's bounding box goes, X,Y,Z in the street frame
    /// [default: a free spot on a sidewalk].
    #[arg(long, value_parser = crate::eval::lidar::sensors::parse_xyz, allow_hyphen_values = true)]
    pub mesh_at: Option<glam::DVec3>,
    /// Scale factor of the mesh [default: its largest extent becomes 1.5 m].
    #[arg(long)]
    pub mesh_scale: Option<f64>,
    /// The mesh's up axis (y: turned to z).
    #[arg(long, value_enum, default_value_t = UpArg::Z)]
    pub mesh_up: UpArg,
    /// The sensor's settings (each keeps the preset's value unless given).
    #[command(flatten)]
    pub sensor_flags: SensorFlags,
    /// Print a JSON summary on standard output.
    #[arg(long)]
    pub json: bool,
    /// Print nothing but errors.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Flags of `qemd score`.
#[derive(Debug, Args)]
pub struct ScoreArgs {
    /// The denoised scan (any readable format; same points in the same order as the truth).
    pub output: PathBuf,
    /// The truth file of `qemd synth lidar --truth`.
    #[arg(long)]
    pub truth: PathBuf,
    /// What went into the denoiser (the noisy scan; with --calm the clean one): adds the input's
    /// errors and the ratios.
    #[arg(long, visible_alias = "input")]
    pub noisy: Option<PathBuf>,
    /// The output denoised the noise-free scan: report each point's move over σ.
    #[arg(long)]
    pub calm: bool,
    /// σ of --calm [default: the truth's].
    #[arg(long)]
    pub sigma: Option<f64>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Flags of `qemd noise`.
#[derive(Debug, Args)]
pub struct NoiseArgs {
    /// Clean input.
    pub input: PathBuf,
    /// Noisy output.
    #[arg(short, long)]
    pub output: PathBuf,
    /// iso (every coordinate) or normal (along the clean normal).
    #[arg(long, default_value = "iso")]
    pub model: String,
    /// σ as a fraction of L (the mean edge length, or mean spacing for clouds).
    #[arg(long, default_value_t = 0.4)]
    pub level: f64,
    /// RNG seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The unit of --level: l (the mean edge length, or mean spacing for clouds) or
    /// median-spacing (the median nearest-neighbour distance, the real-scan protocol's unit).
    #[arg(long, value_enum, default_value_t = NoiseUnit::L)]
    pub unit: NoiseUnit,
}

/// The unit of `qemd noise --level`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum NoiseUnit {
    /// The mean edge length (meshes) or mean nearest-neighbour spacing (clouds).
    L,
    /// The median nearest-neighbour spacing.
    MedianSpacing,
}

/// Flags of `qemd harm`.
#[derive(Debug, Args)]
pub struct HarmArgs {
    /// The method's input: the scan as it is, or with --clean the noisy scan.
    pub input: PathBuf,
    /// The method's output (same points in the same order; any readable format).
    pub output: PathBuf,
    /// The clean scan: measure the noise removed instead of the displacement.
    #[arg(long)]
    pub clean: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Flags of `qemd eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// The clean reference.
    #[arg(long)]
    pub clean: PathBuf,
    /// The denoised file.
    #[arg(long)]
    pub denoised: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Flags of `qemd table`.
#[derive(Debug, Args)]
pub struct TableArgs {
    /// The clean mesh.
    pub clean: PathBuf,
    /// Comma-separated seeds.
    #[arg(long, default_value = "0", value_delimiter = ',')]
    pub seeds: Vec<u64>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Flags of `qemd render`.
#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Mesh or point cloud.
    pub input: PathBuf,
    /// PNG output.
    #[arg(short, long)]
    pub output: PathBuf,
    /// front, side, top, iso, or "AZIMUTH,ELEVATION" in degrees.
    #[arg(long, default_value = "iso")]
    pub view: String,
    /// Image size in pixels, WIDTHxHEIGHT.
    #[arg(long, default_value = "800x800")]
    pub size: String,
    /// The up axis (default: z for LAS, PCD, KITTI and nuScenes, y otherwise).
    #[arg(long, value_enum)]
    pub up: Option<UpArg>,
    /// Colour points by height, intensity or class (default: one colour, shaded by normal).
    #[arg(long, visible_alias = "color", value_enum)]
    pub colour: Option<ColourArg>,
}

/// `qemd render --up`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum UpArg {
    /// +y up.
    Y,
    /// +z up (`--view top` looks down).
    Z,
}

/// `qemd render --colour`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ColourArg {
    /// Height along the up axis.
    Height,
    /// The `intensity` (or `reflectance`) field, 1st to 99th percentile.
    Intensity,
    /// The LAS classification, or a `class`/`label` field (ASPRS colours).
    Class,
}

/// Flags of `qemd demo`.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Folder for the files (created if missing).
    #[arg(long, default_value = "qemd-demo")]
    pub out: PathBuf,
}

/// Flags of `qemd report`.
#[derive(Debug, Args)]
pub struct ReportArgs {
    /// The clean mesh.
    pub clean: PathBuf,
    /// Folder for the report (created if missing).
    #[arg(long, default_value = "qemd-report")]
    pub out: PathBuf,
    /// Comma-separated noise seeds; the tables average over them.
    #[arg(long, default_value = "0,1,2,3,4", value_delimiter = ',')]
    pub seeds: Vec<u64>,
    /// Comma-separated noise levels (σ as a fraction of L) of the tables and charts.
    #[arg(long, default_value = "0.2,0.4,0.8", value_delimiter = ',')]
    pub levels: Vec<f64>,
    /// Folder of the real benchmark pairs (skipped with a note when absent).
    #[arg(long, default_value = crate::eval::pairs::DEFAULT_DIR)]
    pub pairs: PathBuf,
    /// Leave the benchmark pairs out.
    #[arg(long, conflicts_with = "pairs")]
    pub no_pairs: bool,
    /// View of the renderings: front, side, top, iso, or "AZIMUTH,ELEVATION" in degrees.
    #[arg(long, default_value = "iso")]
    pub view: String,
    /// Side of the rendered images in pixels.
    #[arg(long, default_value_t = 420)]
    pub size: u32,
    /// Cells per side of the frequency-response patch.
    #[arg(long, default_value_t = 96)]
    pub patch: usize,
}

/// Flags of `qemd spectrum`.
#[derive(Debug, Args)]
pub struct SpectrumArgs {
    /// Folder for the chart, CSV, summary and renderings (created if missing).
    #[arg(long, default_value = "qemd-spectrum")]
    pub out: PathBuf,
    /// Noise σ along the normal as a fraction of L.
    #[arg(long, default_value_t = 0.4)]
    pub noise: f64,
    /// RNG seed (noise and vertex jitter).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Cells per side of the patch.
    #[arg(long, default_value_t = 96)]
    pub patch: usize,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::denoise::{Method, NormalWeighting, Params, Planes, SolveKind};
    use crate::pipeline::{DEFAULT_OUTLIER_ALPHA, OutlierMode};

    fn params(args: &[&str]) -> Params {
        let cli = Cli::parse_from(
            ["qemd", "denoise", "a.ply", "-o", "b.ply"]
                .iter()
                .chain(args),
        );
        let Command::Denoise(a) = cli.command else {
            panic!("not denoise")
        };
        a.run.spec.resolve(DEFAULT_OUTLIER_ALPHA).unwrap().params
    }

    #[test]
    fn denoise_flags_map_to_params() {
        let p = params(&["--paper", "--rings", "3", "--normals", "mean"]);
        assert_eq!(p.rings, 3);
        assert_eq!(p.normals, NormalWeighting::Mean);
        assert_eq!(p.solve, SolveKind::Plain);
        assert_eq!(p.planes, Planes::Tangent);
        assert_eq!((p.filter, p.updates, p.iterations), (Some(0), Some(1), 1));
        // --paper's base is not overwritten by flags that were not given (the paper clears the
        // volume step; a default for --no-volume must not set it back).
        assert!(!p.volume && !p.guard);
        let q = params(&["--filter", "4", "--no-volume"]);
        assert_eq!(
            (q.filter, q.volume, q.guard, q.planes),
            (Some(4), false, true, Planes::Face)
        );
        assert_eq!(params(&[]), Params::default());
        assert!(!params(&["--no-guard"]).guard);
        assert!(
            Cli::try_parse_from(["qemd", "denoise", "a.ply", "-o", "b", "--format", "doc"])
                .is_err()
        );
    }

    #[test]
    fn issue10_bilateral_from_the_cli_is_the_api_spec() {
        // The CLI stored iterations 0 and the API forced 3; both now leave it to the schedule.
        let cli = params(&["--method", "bilateral"]);
        let api: crate::pipeline::SpecOverlay =
            serde_json::from_value(serde_json::json!({"method": "bilateral"})).unwrap();
        let api = api.resolve(DEFAULT_OUTLIER_ALPHA).unwrap().params;
        assert_eq!(cli, api);
        assert_eq!(cli.method, Method::Bilateral);
        assert_eq!(cli.schedule(true).cycles, 3);
    }

    #[test]
    fn outlier_flags_are_spec_fields() {
        let cli = Cli::parse_from([
            "qemd",
            "denoise",
            "a.ply",
            "-o",
            "b.ply",
            "--outliers",
            "classify",
            "--outlier-alpha",
            "1.5",
        ]);
        let Command::Denoise(a) = cli.command else {
            panic!("not denoise")
        };
        let s = a.run.spec.resolve(DEFAULT_OUTLIER_ALPHA).unwrap();
        assert_eq!((s.outliers, s.outlier_alpha), (OutlierMode::Classify, 1.5));
    }
}
