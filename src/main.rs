//! `qemd`: the command-line front end. Parses flags, dispatches to the library, prints one-line
//! errors and exits non-zero on failure.

use std::io::IsTerminal;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Parser;

use qem_denoise::api::ApiSettings;
use qem_denoise::api::server::{ServeOptions, Server, shutdown_signal};
use qem_denoise::cli::{
    Cli, Command, DemoArgs, DenoiseArgs, EvalArgs, FinishArgs, HarmArgs, InfoArgs, K8sArgs,
    LidarArgs, NoiseArgs, NoiseUnit, PlanArgs, RenderArgs, ReportArgs, ScoreArgs, ServeArgs,
    SpectrumArgs, StatusArgs, SynthArgs, SynthCommand, TableArgs, UpArg, WorkerArgs,
};
use qem_denoise::config::{Config, LogFormat};
use qem_denoise::denoise::{self, Params};
use qem_denoise::eval::Mesh;
use qem_denoise::eval::metrics::{Metrics, Reference};
use qem_denoise::eval::noise::{NoiseModel, NoiseSpec, add_noise};
use qem_denoise::eval::render::{RenderOptions, View, render};
use qem_denoise::eval::report::{ReportSpec, report_methods, write_report};
use qem_denoise::eval::spectrum::{SpectrumSpec, frequency_response, patch_view};
use qem_denoise::eval::synth::Shape;
use qem_denoise::eval::table::{TableSpec, run_table_with_progress};
use qem_denoise::io::{self, BATCH, Cloud, Format, SourceInfo};
use qem_denoise::pipeline::{
    self, BarProgress, Job, LogProgress, NoProgress, Progress, RunOptions,
};
use qem_denoise::points::{PointBatch, ScalarType};

fn main() -> ExitCode {
    one_malloc_arena();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // A file's name or header may hold control characters (ESC, BEL): escaped.
            eprintln!("qemd: error: {}", io::printable(&format!("{e:#}")));
            ExitCode::FAILURE
        }
    }
}

/// Makes glibc's allocator keep one arena for the whole process, unless the environment
/// already chose (`MALLOC_ARENA_MAX`, `GLIBC_TUNABLES`). Why: with one arena per thread (up to 8
/// per core), pages a thread frees stay in its arena where the others cannot reuse them, and a
/// tiled run's peak grew past `--memory-budget` plus the stated constant (3 M cluttered points at
/// 150 MiB: 181–197 MiB; with one arena 133 MiB, at the same CPU time on 2 threads;
/// docs/DECISIONS.md, "One malloc arena"). The only `unsafe` of the project: the library forbids it.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn one_malloc_arena() {
    let chosen = std::env::var_os("MALLOC_ARENA_MAX").is_some()
        || std::env::var("GLIBC_TUNABLES").is_ok_and(|t| t.contains("arena_max"));
    if !chosen {
        // SAFETY: `mallopt` only sets one of the allocator's tunables; it is called first thing
        // in `main`, before the process has a second thread.
        unsafe {
            libc::mallopt(libc::M_ARENA_MAX, 1);
        }
    }
}

/// Other platforms keep their allocator's defaults.
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn one_malloc_arena() {}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Denoise(a) => denoise(*a),
        Command::Info(a) => info(&a),
        Command::Synth(a) => synth(a),
        Command::Score(a) => score(a),
        Command::Noise(a) => noise(a),
        Command::Harm(a) => harm(a),
        Command::Eval(a) => eval(a),
        Command::Table(a) => table(a),
        Command::Render(a) => render_cmd(a),
        Command::Demo(a) => demo(a),
        Command::Report(a) => report(a),
        Command::Spectrum(a) => spectrum(a),
        Command::Serve(a) => serve(a),
        Command::Plan(a) => plan(*a),
        Command::Worker(a) => worker(a),
        Command::Finish(a) => finish(a),
        Command::Status(a) => status(a),
        Command::K8s(a) => k8s(a),
    }
}

/// The progress display of a command: none when quiet, a bar on a terminal, else log lines.
fn progress_for(quiet: bool) -> Arc<dyn Progress> {
    if quiet {
        Arc::new(NoProgress)
    } else if std::io::stderr().is_terminal() {
        Arc::new(BarProgress::default())
    } else {
        Arc::new(LogProgress::new(Duration::from_secs(10)))
    }
}

/// A cancel flag set by Ctrl-C and SIGTERM (what `scancel` and a pod's deletion send first).
fn cancel_flag() -> Result<Arc<AtomicBool>> {
    let cancel = Arc::new(AtomicBool::new(false));
    let c = cancel.clone();
    ctrlc::set_handler(move || c.store(true, Ordering::Relaxed))
        .context("cannot install the Ctrl-C handler")?;
    Ok(cancel)
}

fn plan(a: PlanArgs) -> Result<()> {
    use qem_denoise::pipeline::scaleout::{self, Phase, PlanRequest, WorkUrl};
    init_threads(a.run.threads)?;
    let config = Config::load(a.run.config.as_deref())?;
    let work = WorkUrl::parse(&a.work)?;
    let (input_format, output_format) = a.formats();
    let req = PlanRequest {
        input: a.input.clone(),
        input_format,
        output_format,
        spec: a.run.spec.resolve(config.outlier_alpha)?,
        memory_budget: a.run.memory_budget.unwrap_or(config.memory_budget).as_u64(),
        tile_points: a.run.tile_points,
        part_points: a.run.part_points,
        stored_as: None,
        stitch_tasks: true,
    };
    let hooks = scaleout::Hooks {
        progress: progress_for(a.quiet),
        cancel: cancel_flag()?,
    };
    let planned = qem_denoise::objects::plan(&work, &req, &hooks);
    hooks.progress.finish();
    let planned = planned?;
    let tasks = planned.job.tasks();
    if a.json {
        let phases: serde_json::Map<String, serde_json::Value> = Phase::ALL
            .iter()
            .zip(tasks)
            .map(|(p, n)| (p.name().to_string(), n.into()))
            .collect();
        let out = serde_json::json!({
            "work": work.to_string(),
            "input": planned.job.input,
            "points": planned.job.plan.points,
            "tiles": planned.job.plan.tiles.len(),
            "existing": planned.existing,
            "tasks": phases,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else if !a.quiet {
        if planned.existing {
            eprintln!("qemd: {work} already holds this job; nothing changed");
        }
        println!(
            "{}, {} in {work}",
            count(planned.job.plan.points, ["point", "points"]),
            count(planned.job.plan.tiles.len() as u64, ["tile", "tiles"])
        );
        for (p, n) in Phase::ALL.iter().zip(tasks) {
            println!("{:<10} {n} tasks", p.name());
        }
    }
    Ok(())
}

fn worker(a: WorkerArgs) -> Result<()> {
    use qem_denoise::pipeline::scaleout::{Hooks, WorkUrl};
    init_threads(a.threads)?;
    let work = WorkUrl::parse(&a.work)?;
    let hooks = Hooks {
        progress: progress_for(a.quiet || a.json),
        cancel: cancel_flag()?,
    };
    let r = qem_denoise::objects::run_task(
        &work,
        a.phase,
        (a.index, a.of),
        |k| std::env::var(k).ok(),
        &hooks,
    );
    hooks.progress.finish();
    let r = r?;
    if a.json {
        println!("{}", serde_json::to_string(&r)?);
    } else if !a.quiet {
        eprintln!(
            "qemd: {} task {} of {} ({}): {} assigned, {} done, {} already committed, {:.3} s",
            r.phase,
            r.task.index,
            r.task.of,
            r.task.source,
            r.assigned,
            r.done,
            r.skipped,
            r.wall_s
        );
    }
    Ok(())
}

fn finish(a: FinishArgs) -> Result<()> {
    use qem_denoise::pipeline::scaleout::{Hooks, WorkUrl};
    init_threads(a.threads)?;
    let work = WorkUrl::parse(&a.work)?;
    let hooks = Hooks {
        progress: progress_for(a.quiet),
        cancel: cancel_flag()?,
    };
    let f = qem_denoise::objects::finish(&work, &a.output, a.format, &hooks);
    hooks.progress.finish();
    let f = f?;
    if !a.quiet {
        eprintln!(
            "qemd: {work} → {} ({}): {} in, {} out, {} outliers, {}",
            f.output.display(),
            f.delivered,
            count(f.points_in, ["point", "points"]),
            f.written,
            f.found,
            count(f.tiles, ["tile", "tiles"])
        );
        if f.normals == pipeline::NormalsAction::Cleared {
            eprintln!(
                "qemd: warning: the input's stored normals would be stale after denoising and were cleared (NaN); recompute them downstream"
            );
        }
        if f.dropped > 0 {
            eprintln!(
                "qemd: warning: {} points with NaN, infinite or out-of-range (beyond ±1e12) coordinates were dropped",
                f.dropped
            );
        }
    }
    Ok(())
}

fn k8s(a: K8sArgs) -> Result<()> {
    use qem_denoise::pipeline::scaleout::WorkUrl;
    use std::io::Write;
    let work = WorkUrl::parse(&a.work)?;
    if !matches!(work, WorkUrl::S3 { .. }) {
        // Refused before the plan is read (the same error the manifests give).
        qem_denoise::k8s::manifests(&work, |_| 0, 0, &a.options())?;
    }
    let job = qem_denoise::objects::job(&work)?;
    let manifests =
        qem_denoise::k8s::manifests(&work, |p| job.tasks_of(p), job.memory_budget, &a.options())?;
    match &a.output {
        None => {
            let mut out = std::io::stdout().lock();
            for m in &manifests {
                match write!(out, "---\n{}", m.to_yaml()?) {
                    // A reader that stopped early (`| head`) is not an error.
                    Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => return Ok(()),
                    r => r?,
                }
            }
        }
        Some(dir) => {
            std::fs::create_dir_all(dir).with_context(|| format!("{}", dir.display()))?;
            for m in &manifests {
                let path = dir.join(m.file_name());
                let mut f = qem_denoise::io::output::AtomicFile::create(&path)?;
                f.write_all(m.to_yaml()?.as_bytes()).map_err(|e| f.err(e))?;
                f.commit()?;
                println!("{}", path.display());
            }
        }
    }
    Ok(())
}

fn status(a: StatusArgs) -> Result<()> {
    use qem_denoise::pipeline::scaleout::WorkUrl;
    let work = WorkUrl::parse(&a.work)?;
    let s = qem_denoise::objects::status(&work)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
        return Ok(());
    }
    println!(
        "{}: {}, {}",
        s.work,
        count(s.points, ["point", "points"]),
        count(s.tiles, ["tile", "tiles"])
    );
    for p in &s.phases {
        let state = if p.units == 0 {
            "not needed".to_string()
        } else if p.complete() {
            "done".to_string()
        } else {
            "pending".to_string()
        };
        println!(
            "{:<10} {:>6} tasks {:>6}/{:<6} committed  {state}",
            p.phase.name(),
            p.tasks,
            p.committed,
            p.units
        );
    }
    match s.next {
        Some(p) => println!("next: {p}"),
        None => println!("next: qemd finish"),
    }
    Ok(())
}

fn init_logging(config: &Config) -> Result<()> {
    let filter = tracing_subscriber::EnvFilter::try_new(&config.log_level)
        .with_context(|| format!("log_level `{}` is not a valid filter", config.log_level))?;
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal());
    let installed = match config.log_format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
    installed.map_err(|e| anyhow::anyhow!("cannot install the logger: {e}"))
}

fn serve(a: ServeArgs) -> Result<()> {
    use std::io::Write;
    let mut config = Config::load(a.config.as_deref())?;
    if let Some(l) = a.listen {
        config.listen = l;
    }
    if let Some(d) = a.data_dir {
        config.data_dir = d;
    }
    config.validate_service()?;
    init_logging(&config)?;
    let opts = ServeOptions {
        listen: config.listen.clone(),
        jobs: qem_denoise::jobs::Settings {
            data_dir: config.data_dir.clone(),
            job_concurrency: config.job_concurrency,
            queue_capacity: config.queue_capacity,
            memory_budget: config.memory_budget.as_u64(),
            job_tile_points: config.job_tile_points,
            outlier_alpha: config.outlier_alpha,
            max_upload_size: config.max_upload_size.as_u64(),
            sync_concurrency: config.sync_concurrency,
            preview_points: config.preview_points,
            job_time_limit: config.job_time_limit,
            sync_time_limit: config.sync_time_limit,
            slurm: slurm_settings(&config),
        },
        api: ApiSettings {
            tokens: config.tokens()?,
            max_sync_size: config.max_sync_size.as_u64(),
        },
        grace: Duration::from_secs(10),
        connections: qem_denoise::api::conn::ConnLimits {
            header: config.header_read_timeout,
            body: config.body_read_timeout,
            per_address: config.max_connections_per_address,
        },
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("qemd-io")
        .build()
        .context("cannot start the async runtime")?;
    let result = runtime.block_on(async move {
        let server = Server::bind(opts).await?;
        let addr = server.local_addr()?;
        // The one line a supervisor (or a test) reads to learn the bound address.
        println!("qemd: listening on http://{addr}");
        std::io::stdout().flush()?;
        server.run(shutdown_signal()).await?;
        anyhow::Ok(())
    });
    runtime.shutdown_timeout(Duration::from_secs(2));
    result
}

/// The SLURM executor's settings when the configuration says `executor = "slurm"`.
fn slurm_settings(config: &Config) -> Option<qem_denoise::jobs::slurm::SlurmSettings> {
    use qem_denoise::config::Executor;
    let name = |s: &str| (!s.is_empty()).then(|| s.to_string());
    (config.executor == Executor::Slurm).then(|| qem_denoise::jobs::slurm::SlurmSettings {
        min_points: config.slurm_min_points,
        worker: (!config.slurm_worker.as_os_str().is_empty()).then(|| config.slurm_worker.clone()),
        partition: name(&config.slurm_partition),
        account: name(&config.slurm_account),
        cpus_per_task: config.slurm_cpus_per_task,
        max_tasks: config.slurm_max_tasks,
        sbatch_args: config.sbatch_args(),
        poll_interval: config.slurm_poll_interval,
        client: qem_denoise::jobs::slurm::Client::default(),
    })
}

/// `n` and the noun `[one, many]` its number takes (`1 tile`, `3 tiles`).
fn count(n: u64, [one, many]: [&str; 2]) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// What a run's points are: a mesh's vertices or a cloud's points.
fn unit(report: &pipeline::Report) -> [&'static str; 2] {
    if report.mode == "mesh" {
        ["vertex", "vertices"]
    } else {
        ["point", "points"]
    }
}

/// Why a point run that read points moved none of them, when the input's stored coordinate
/// grid explains it: the scan noise estimate `noise` (which bounds every guarded step) is below
/// the grid's coarsest axis, so nearby returns share their stored values and look noiseless
/// (issue 51: `f32` E57 coordinates at UTM magnitude are 0.5 apart in northing). `None` when
/// something moved, the input cannot be read again (a stream) or its grid is finer than the
/// noise.
fn nothing_moved(report: &pipeline::Report, job: &Job, noise: f64) -> Option<String> {
    if report.mode == "mesh" || report.stats.moved > 0 || report.points_in == 0 {
        return None;
    }
    if io::is_stream_input(&job.input) {
        return None;
    }
    let grid = io::resolution::coordinate_resolution(&job.input, job.input_format).ok()?;
    let coarsest = grid.into_iter().fold(0.0, f64::max);
    (noise < coarsest).then(|| {
        format!(
            "qemd: nothing moved: the scan noise estimate {noise:.3e} is below the input's coordinate resolution (x {:.3e}, y {:.3e}, z {:.3e} input units, the smallest step between stored values), so nearby points share their stored values and every step is bounded to zero; store the coordinates more finely (doubles, or scaled integers with an offset near the data, as LAS does) — f32 coordinates at UTM magnitudes are this coarse",
            grid[0], grid[1], grid[2]
        )
    })
}

/// How a run went, for its summary: `mesh, 1200 faces`, `point cloud in memory`, `point cloud
/// in 3 tiles`.
fn run_kind(report: &pipeline::Report) -> String {
    match report.mode.as_str() {
        "mesh" => format!("mesh, {}", count(report.faces, ["face", "faces"])),
        "tiled" => format!("point cloud in {}", count(report.tiles, ["tile", "tiles"])),
        _ => "point cloud in memory".to_string(),
    }
}

fn info(a: &InfoArgs) -> Result<()> {
    let config = Config::load(None)?;
    let info = qem_denoise::info::inspect(&a.input, a.format(), config.temp_dir().as_deref())?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&info)?);
    } else {
        print!("{info}");
    }
    Ok(())
}

fn init_threads(threads: Option<usize>) -> Result<()> {
    if let Some(n) = threads {
        anyhow::ensure!(n >= 1, "--threads must be at least 1");
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .context("cannot start the thread pool")?;
    }
    Ok(())
}

fn denoise(a: DenoiseArgs) -> Result<()> {
    init_threads(a.run.threads)?;
    let config = Config::load(a.run.config.as_deref())?;
    let (input_format, output_format) = a.formats();
    let job = Job {
        input: a.input.clone(),
        output: a.output.clone(),
        input_format,
        output_format,
        spec: a.run.spec.resolve(config.outlier_alpha)?,
        trajectory: a.trajectory.clone(),
    };
    let progress: Arc<dyn Progress> = if a.quiet {
        Arc::new(NoProgress)
    } else if std::io::stderr().is_terminal() {
        Arc::new(BarProgress::default())
    } else {
        Arc::new(LogProgress::new(Duration::from_secs(10)))
    };
    let cancel = Arc::new(AtomicBool::new(false));
    {
        // Ctrl-C and SIGTERM stop the run at the next batch or tile; the temporary directory and
        // the unfinished output are then removed as the run unwinds.
        let cancel = cancel.clone();
        ctrlc::set_handler(move || cancel.store(true, Ordering::Relaxed))
            .context("cannot install the Ctrl-C handler")?;
    }
    let opts = RunOptions {
        memory_budget: a.run.memory_budget.unwrap_or(config.memory_budget).as_u64(),
        temp_dir: a.temp_dir.clone().or_else(|| config.temp_dir()),
        tile_points: a.run.tile_points,
        part_points: a.run.part_points,
        progress: progress.clone(),
        cancel,
        work_dir: None,
    };
    let report = pipeline::run(&job, &opts);
    progress.finish();
    let report = report?;
    if let Some(path) = &a.report {
        report.write(path)?;
    }
    if !a.quiet {
        let s = &report.stats;
        eprintln!(
            "qemd: {} → {}: {}, {} in, {} out ({} moved, {} stayed singular, {} degenerate, {} duplicates, {} outliers), {:.3} s wall / {:.3} s CPU, peak RSS {:.1} MiB",
            io::printable(&report.input.to_string_lossy()),
            io::printable(&report.output.to_string_lossy()),
            run_kind(&report),
            count(report.points_in, unit(&report)),
            report.points_out,
            s.moved,
            s.singular,
            s.degenerate_neighbourhoods,
            s.duplicates,
            report.outliers_found,
            report.wall_s,
            report.cpu_s,
            report.peak_rss_bytes as f64 / (1024.0 * 1024.0),
        );
        if report.mode != "mesh" {
            let c = &s.structure;
            let classes = if c.surface + c.edge + c.line + c.scatter + c.sparse + c.degenerate > 0 {
                format!(
                    "; neighbourhoods: {} surface, {} edge, {} line, {} scatter, {} sparse, {} degenerate",
                    c.surface, c.edge, c.line, c.scatter, c.sparse, c.degenerate
                )
            } else {
                String::new()
            };
            let held = if s.held > 0 {
                format!(
                    ", {} held by class (--classes; LAS noise and withheld)",
                    s.held
                )
            } else {
                String::new()
            };
            eprintln!(
                "qemd: displacement p50 {:.3e} / p99 {:.3e} / max {:.3e} (input units); {} bounded, {} isolated{held}{classes}",
                s.displacement.p50, s.displacement.p99, s.displacement.max, s.bounded, s.isolated
            );
        }
        if let Some(noise) = s.noise_estimate {
            let beams = match report.params.sensor_origin.point() {
                Some(o) => format!("along the beams from {},{},{}", o.x, o.y, o.z),
                None => "no beams (--sensor-origin X,Y,Z gives them)".into(),
            };
            eprintln!(
                "qemd: scan noise estimate {noise:.3e} (input units), {beams}; {} steps bounded",
                s.bounded
            );
            if let Some(why) = nothing_moved(&report, &job, noise) {
                eprintln!("{why}");
            }
        }
        if report.normals == pipeline::NormalsAction::Cleared {
            eprintln!(
                "qemd: warning: the input's stored normals would be stale after denoising and were cleared (NaN); recompute them downstream"
            );
        }
        if report.normals == pipeline::NormalsAction::Recomputed {
            eprintln!("qemd: the stored normals were recomputed from the denoised faces");
        }
        if report.normals == pipeline::NormalsAction::Written {
            eprintln!(
                "qemd: wrote each point's normal, curvature and structure class as fields (--write-normals)"
            );
        }
        if report.dropped_non_finite > 0 {
            eprintln!(
                "qemd: warning: {} points with NaN, infinite or out-of-range (beyond ±1e12) coordinates were dropped",
                report.dropped_non_finite
            );
        }
    }
    Ok(())
}

fn synth(a: SynthArgs) -> Result<()> {
    if let Some(SynthCommand::Lidar(l)) = a.command {
        return lidar(*l);
    }
    let (Some(shape), Some(output)) = (a.shape, a.output) else {
        anyhow::bail!("qemd synth needs a shape and -o (or the `lidar` subcommand)");
    };
    let a = SynthShape {
        shape,
        output,
        resolution: a.resolution,
        points: a.points,
        seed: a.seed,
    };
    let shape: Shape = a.shape.parse()?;
    let resolution = match a.resolution {
        Some(r) => u32::try_from(r).context("--resolution is too large")?,
        None => shape.default_resolution(),
    };
    match a.points {
        None => {
            let mesh = shape.mesh(resolution)?;
            let (v, f) = (mesh.positions.len(), mesh.faces.len());
            mesh.into_cloud().write(&a.output, None)?;
            eprintln!(
                "qemd: wrote {shape} mesh, {v} vertices, {f} faces, to {}",
                a.output.display()
            );
        }
        Some(n) => {
            // Streams: one batch of samples at a time, whatever n is.
            let mut sampler = shape.sampler(resolution, n, a.seed)?;
            let format = Format::from_path(&a.output)?;
            let info = SourceInfo::generated(format, ScalarType::F32, n, None);
            let mut sink = io::create(&a.output, None, &info, n)?;
            let rl = info.schema.record_len;
            let mut pts = Vec::with_capacity(BATCH);
            let mut batch = PointBatch::with_capacity(rl, BATCH);
            let mut start = 0u64;
            while sampler.fill(&mut pts, BATCH) > 0 {
                batch.clear(start);
                batch.positions.extend_from_slice(&pts);
                batch.records.resize(pts.len() * rl, 0);
                sink.write_batch(&batch)?;
                start += pts.len() as u64;
                pts.clear();
            }
            sink.finish(&io::Extras::default())?;
            eprintln!(
                "qemd: wrote {n} samples of {shape} to {}",
                a.output.display()
            );
        }
    }
    Ok(())
}

/// `qemd synth SHAPE` once the subcommand is ruled out.
struct SynthShape {
    shape: String,
    output: std::path::PathBuf,
    resolution: Option<usize>,
    points: Option<u64>,
    seed: u64,
}

fn lidar(a: LidarArgs) -> Result<()> {
    use qem_denoise::eval::lidar::{self, LidarSpec, StreetSpec, writers};
    let started = std::time::Instant::now();
    let format = writers::scan_format(&a.output)?;
    for p in [&a.clean].into_iter().flatten() {
        writers::scan_format(p)?;
    }
    let object = match a.object.as_str() {
        "none" => None,
        s => Some(s.parse::<Shape>()?),
    };
    let mesh = match &a.mesh {
        Some(path) => {
            let cloud = Cloud::read(path, None)?;
            let faces = cloud.faces().cloned().with_context(|| {
                format!("{}: --mesh needs a mesh (no faces found)", path.display())
            })?;
            Some(lidar::street::PlacedMesh {
                positions: cloud.positions,
                faces,
                at: a.mesh_at,
                scale: a.mesh_scale,
                y_up: a.mesh_up == UpArg::Y,
            })
        }
        None => None,
    };
    let spec = LidarSpec {
        sensor: a.sensor,
        flags: a.sensor_flags.clone(),
        street: StreetSpec {
            length: a.length,
            object,
            mesh,
        },
        seed: a.seed,
        scene_seed: a.scene_seed.unwrap_or(a.seed),
        frame: a.frame,
    };
    let sim = lidar::simulate(&spec, format)?;
    sim.write_scan(&a.output, false)?;
    if let Some(p) = &a.clean {
        sim.write_scan(p, true)?;
    }
    if let Some(p) = &a.truth {
        sim.truth(spec.seed, spec.scene_seed).write(p)?;
    }
    let trajectory = sim.trajectory();
    if let Some(p) = &a.trajectory_out {
        trajectory.write(p)?;
    }
    let per_kind = sim.returns_per_kind();
    let mixed = sim.returns.iter().filter(|r| r.mixed).count();
    let offcentre = sim.returns.iter().filter(|r| r.offcentre).count();
    let origin = trajectory.samples.first().map(|s| s.1);
    let summary = serde_json::json!({
        "sensor": sim.sensor_name(),
        "pulses": sim.pulses.len(),
        "returns": sim.returns.len(),
        "mixed": mixed,
        "offcentre": offcentre,
        "per_kind": per_kind.iter().map(|(k, n)| (k.name().to_string(), *n)).collect::<std::collections::BTreeMap<_, _>>(),
        "triangles": sim.street.scene.triangles.len(),
        "frame": sim.frame,
        "frame_origin": sim.frame_origin.to_array(),
        "sensor_origin": origin.map(|o| o.to_array()),
        "physics": sim.sensor.physics,
        "geometry": sim.sensor.geometry,
        "layout": sim.street.layout,
        "seconds": started.elapsed().as_secs_f64(),
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    }
    if !a.quiet {
        let kinds: Vec<String> = per_kind.iter().map(|(k, n)| format!("{k} {n}")).collect();
        eprintln!(
            "qemd: {} over a {} m street (scene seed {}, seed {}): {} returns of {} pulses \
             ({mixed} mixed, {offcentre} off-centre; {}) in {:.1} s",
            sim.sensor_name(),
            a.length,
            spec.scene_seed,
            spec.seed,
            sim.returns.len(),
            sim.pulses.len(),
            kinds.join(", "),
            started.elapsed().as_secs_f64()
        );
        if let Some(o) = origin {
            let fixed = trajectory.samples.iter().all(|s| s.1 == o);
            eprintln!(
                "qemd: frame {:?}; sensor origin {} {},{},{} (σ = {} m)",
                sim.frame,
                if fixed { "at" } else { "starts at" },
                o.x,
                o.y,
                o.z,
                sim.sensor.physics.sigma
            );
        }
    }
    Ok(())
}

fn score(a: ScoreArgs) -> Result<()> {
    use qem_denoise::eval::lidar::{Truth, score::ScoreSpec};
    let truth = Truth::read(&a.truth)?;
    let output = Cloud::read(&a.output, None)?;
    let input = match &a.noisy {
        Some(p) => Some(Cloud::read(p, None)?),
        None => None,
    };
    let s = qem_denoise::eval::lidar::score(
        &truth,
        &output,
        &a.output,
        input.as_ref().zip(a.noisy.as_deref()),
        ScoreSpec {
            calm: a.calm,
            sigma: a.sigma,
        },
    )?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        print!("{}", s.table());
    }
    Ok(())
}

fn noise(a: NoiseArgs) -> Result<()> {
    let model = match a.model.as_str() {
        "iso" => NoiseModel::Iso,
        "normal" => NoiseModel::Normal,
        other => anyhow::bail!("--model must be iso or normal, not `{other}`"),
    };
    let spec = NoiseSpec {
        model,
        level: a.level,
        seed: a.seed,
    };
    spec.validate()?;
    let mut cloud = Cloud::read(&a.input, None)?;
    let noisy = match a.unit {
        NoiseUnit::L => add_noise(&cloud.positions, cloud.faces(), &spec),
        NoiseUnit::MedianSpacing => qem_denoise::eval::scans::median_spacing(&cloud.positions)
            .and_then(|l| {
                qem_denoise::eval::add_noise_with_length(&cloud.positions, cloud.faces(), &spec, l)
            }),
    }
    .with_context(|| a.input.display().to_string())?;
    cloud.positions = noisy.positions;
    cloud.write(&a.output, None)?;
    eprintln!(
        "qemd: {}",
        noise_summary(noisy.displaced, a.level, noisy.sigma, noisy.l)
    );
    Ok(())
}

/// The line `qemd noise` prints: σ is `level × L`, and L is printed on its own.
fn noise_summary(displaced: usize, level: f64, sigma: f64, l: f64) -> String {
    format!("{displaced} points displaced with σ = {level} × L = {sigma:.6e} (L = {l:.6e})")
}

fn harm(a: HarmArgs) -> Result<()> {
    use qem_denoise::eval::scans;
    let input = Cloud::read(&a.input, None)?;
    let output = Cloud::read(&a.output, None)?;
    let ctx = || a.output.display().to_string();
    match &a.clean {
        None => {
            let classes =
                scans::classes_of(&input).with_context(|| a.input.display().to_string())?;
            let h = scans::harm(&input, &output, &classes).with_context(ctx)?;
            if let qem_denoise::eval::pairing::Pairing::Attributes {
                fields,
                by_position,
            } = &h.pairing
            {
                eprintln!(
                    "qemd: {} is reordered; its points were paired by {} ({by_position} points \
                     alike in those by position)",
                    a.output.display(),
                    fields.join(", ")
                );
            }
            if a.json {
                println!("{}", serde_json::to_string_pretty(&h)?);
            } else {
                println!(
                    "{:<24} {:>9} {:>8} {:>8} {:>8} {:>10} {:>10}",
                    "class", "points", "p50/r16", "p99/r16", "max/r16", "p99", "max"
                );
                for r in &h.rows {
                    println!(
                        "{:<24} {:>9} {:>8.3} {:>8.3} {:>8.3} {:>10.4} {:>10.4}",
                        r.name,
                        r.count,
                        r.relative.p50,
                        r.relative.p99,
                        r.relative.max,
                        r.absolute.p99,
                        r.absolute.max
                    );
                }
            }
        }
        Some(c) => {
            let clean = Cloud::read(c, None)?;
            let classes = scans::classes_of(&clean).with_context(|| c.display().to_string())?;
            let n = scans::noise_removed(&clean, &input, &output, &classes).with_context(ctx)?;
            if a.json {
                println!("{}", serde_json::to_string_pretty(&n)?);
            } else {
                println!(
                    "{:<24} {:>9} {:>11} {:>11} {:>7}",
                    "class", "points", "rms noisy", "rms out", "ratio"
                );
                for r in n.rows.iter().chain(std::iter::once(&n.planar)) {
                    println!(
                        "{:<24} {:>9} {:>11.4e} {:>11.4e} {:>7.3}",
                        r.name, r.count, r.noisy, r.denoised, r.ratio
                    );
                }
            }
        }
    }
    Ok(())
}

fn measure(clean: &Cloud, denoised: &Cloud) -> Result<Metrics> {
    let reference = Reference::new(clean.positions.clone(), clean.faces().cloned())?;
    Ok(reference.evaluate(&denoised.positions, denoised.faces())?)
}

fn eval(a: EvalArgs) -> Result<()> {
    let clean = Cloud::read(&a.clean, None)?;
    let denoised = Cloud::read(&a.denoised, None)?;
    let m = measure(&clean, &denoised)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&m)?);
    } else {
        print!("{m}");
    }
    Ok(())
}

fn table(a: TableArgs) -> Result<()> {
    let clean = Cloud::read(&a.clean, None)?;
    let faces = clean.faces().with_context(|| {
        format!(
            "{}: Table I needs a mesh (no faces found)",
            a.clean.display()
        )
    })?;
    let spec = TableSpec {
        seeds: a.seeds.clone(),
        ..TableSpec::default()
    };
    let t = run_table_with_progress(&clean.positions, faces, &spec, &mut |p| {
        eprintln!(
            "qemd: [{}/{}] level {:.0} % seed {} {}: surf_std {:.2}",
            p.done,
            p.total,
            p.level * 100.0,
            p.seed,
            p.method,
            p.metrics.surf_std.unwrap_or(f64::NAN)
        );
    })?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&t)?);
    } else {
        print!("{}", t.to_markdown());
    }
    Ok(())
}

fn render_options(view: &str, size: &str) -> Result<RenderOptions> {
    let view: View = view.parse()?;
    let (w, h) = size
        .split_once(['x', 'X'])
        .and_then(|(w, h)| Some((w.trim().parse().ok()?, h.trim().parse().ok()?)))
        .with_context(|| format!("--size must be WIDTHxHEIGHT, not `{size}`"))?;
    let o = RenderOptions {
        width: w,
        height: h,
        view,
        ..RenderOptions::default()
    };
    o.validate()?;
    Ok(o)
}

fn render_cmd(a: RenderArgs) -> Result<()> {
    use qem_denoise::cli::{ColourArg, UpArg};
    use qem_denoise::eval::render::{ColourBy, Up, render_with};
    let mut options = render_options(&a.view, &a.size)?;
    let cloud = Cloud::read(&a.input, None)?;
    options.up = match a.up {
        Some(UpArg::Y) => Up::Y,
        Some(UpArg::Z) => Up::Z,
        None => Up::of_format(cloud.info.format),
    };
    options.colour_by = a.colour.map(|c| match c {
        ColourArg::Height => ColourBy::Height,
        ColourArg::Intensity => ColourBy::Intensity,
        ColourArg::Class => ColourBy::Class,
    });
    let values =
        render_values(&cloud, options.colour_by).with_context(|| a.input.display().to_string())?;
    let image = render_with(&cloud.positions, cloud.faces(), values.as_deref(), &options)
        .with_context(|| a.input.display().to_string())?;
    image.save(&a.output)?;
    Ok(())
}

/// The per-point values `--colour intensity|class` reads from the file's records.
fn render_values(
    cloud: &Cloud,
    by: Option<qem_denoise::eval::render::ColourBy>,
) -> Result<Option<Vec<f64>>> {
    use qem_denoise::eval::render::ColourBy;
    use qem_denoise::eval::scans::{ClassSource, classes_of};
    let schema = &cloud.info.schema;
    let rl = schema.record_len.max(1);
    match by {
        Some(ColourBy::Intensity) => {
            let field = ["intensity", "reflectance", "scalar_intensity", "i"]
                .iter()
                .find_map(|n| schema.field_index(n));
            Ok(field.map(|i| {
                cloud
                    .records
                    .chunks_exact(rl)
                    .map(|r| schema.get_f64(r, i))
                    .collect()
            }))
        }
        Some(ColourBy::Class) => {
            let has_field = ["classification", "class", "label"]
                .iter()
                .any(|n| schema.field_index(n).is_some());
            if !has_field {
                return Ok(None);
            }
            let c = classes_of(cloud)?;
            Ok((c.source != ClassSource::Structure)
                .then(|| c.codes.iter().map(|&v| f64::from(v)).collect()))
        }
        _ => Ok(None),
    }
}

fn demo(a: DemoArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create the folder", a.out.display()))?;
    // A CAD-like part with straight and circular sharp edges, scanned with 40 % noise.
    let clean = Shape::Csg.mesh(48)?;
    let spec = NoiseSpec {
        model: NoiseModel::Iso,
        level: 0.4,
        seed: 7,
    };
    let noisy = add_noise(&clean.positions, Some(&clean.faces), &spec)?;
    let params = Params::default();
    let out = denoise::denoise(&noisy.positions, Some(&clean.faces), &params)?;
    let reference = Reference::new(clean.positions.clone(), Some(clean.faces.clone()))?;
    let before = reference.evaluate(&noisy.positions, Some(&clean.faces))?;
    let after = reference.evaluate(&out.positions, Some(&clean.faces))?;

    let options = RenderOptions {
        view: View::Angles {
            azimuth: 35.0,
            elevation: 30.0,
        },
        ..RenderOptions::default()
    };
    let files = [("noisy", &noisy.positions), ("denoised", &out.positions)];
    for (name, pos) in files {
        let cloud = Cloud::generated(pos.clone(), Some(clean.faces.clone()), ScalarType::F64);
        cloud.write(&a.out.join(format!("{name}.ply")), None)?;
        render(pos, Some(&clean.faces), &options)?.save(&a.out.join(format!("{name}.png")))?;
    }
    println!(
        "qemd demo: CSG part, {} vertices, iso noise σ = 0.4 L, QEM with default parameters",
        clean.positions.len(),
    );
    println!(
        "{:<10}{:>12}{:>12}{:>12}",
        "", "surf_std", "std_xyz", "ang_deg"
    );
    for (name, m) in [("noisy", &before), ("denoised", &after)] {
        println!(
            "{name:<10}{:>11.2}%{:>11.2}%{:>11.2}°",
            m.surf_std.unwrap_or(f64::NAN),
            m.std_xyz.unwrap_or(f64::NAN),
            m.ang_deg.unwrap_or(f64::NAN)
        );
    }
    println!(
        "wrote noisy.ply, denoised.ply, noisy.png and denoised.png to {}",
        a.out.display()
    );
    Ok(())
}

/// The command line as typed, for the report's "regenerate with" line.
fn command_line() -> String {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .map(|a| {
            if !a.is_empty()
                && a.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_./,=:+".contains(c))
            {
                a
            } else {
                format!("'{}'", a.replace('\'', "'\\''"))
            }
        })
        .collect();
    format!("cargo run --release -- {}", args.join(" "))
}

fn report(a: ReportArgs) -> Result<()> {
    let cloud = Cloud::read(&a.clean, None)?;
    let faces = cloud
        .faces()
        .filter(|f| !f.is_empty())
        .cloned()
        .with_context(|| {
            format!(
                "{}: the report needs a mesh (no faces found)",
                a.clean.display()
            )
        })?;
    let mesh = Mesh {
        positions: cloud.positions,
        faces,
    };
    let defaults = ReportSpec::default();
    let spec = ReportSpec {
        title: a.clean.file_name().map_or_else(
            || a.clean.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        ),
        command: Some(command_line()),
        seeds: a.seeds.clone(),
        levels: a.levels.clone(),
        render: render_options(&a.view, &format!("{0}x{0}", a.size))?,
        pairs_dir: (!a.no_pairs).then(|| a.pairs.clone()),
        spectrum: Some(SpectrumSpec {
            cells: a.patch,
            ..SpectrumSpec::default()
        }),
        ..defaults
    };
    let report = write_report(&mesh, &spec, &a.out, &mut |s| eprintln!("qemd: {s}"))?;
    print!("{}", report.table.to_markdown());
    eprintln!(
        "qemd: wrote {} files; open {}",
        report.files.len(),
        a.out.join("index.html").display()
    );
    Ok(())
}

fn spectrum(a: SpectrumArgs) -> Result<()> {
    let spec = SpectrumSpec {
        cells: a.patch,
        noise: NoiseSpec {
            model: NoiseModel::Normal,
            level: a.noise,
            seed: a.seed,
        },
    };
    let r = frequency_response(&spec, &report_methods())?;
    let options = RenderOptions {
        width: 420,
        height: 420,
        view: patch_view(),
        ..RenderOptions::default()
    };
    let files = r.write(&a.out, Some(&options))?;
    print!("{}", r.summary());
    eprintln!("qemd: wrote {} files to {}", files.len(), a.out.display());
    Ok(())
}
