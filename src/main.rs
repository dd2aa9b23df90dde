//! `qemd`: the command-line front end. Parses flags, dispatches to the library, prints one-line
//! errors and exits non-zero on failure.

use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Parser;

use qem_denoise::cli::{Cli, Command, DenoiseArgs};
use qem_denoise::pipeline::{self, Job};

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("qemd: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Denoise(a) => denoise(a),
        other => anyhow::bail!("{other:?} is not available yet"),
    }
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
    init_threads(a.threads)?;
    let job = Job {
        input: a.input.clone(),
        output: a.output.clone(),
        input_format: a.input_format,
        output_format: a.format,
        params: a.params(),
    };
    let report = pipeline::run(&job)?;
    if let Some(path) = &a.report {
        report.write(path)?;
    }
    if !a.quiet {
        let s = &report.stats;
        eprintln!(
            "qemd: {} → {}: {} {} points ({} moved, {} stayed singular, {} degenerate, {} duplicates, {} non-finite dropped) in {:.3} s wall / {:.3} s CPU, peak RSS {:.1} MiB",
            report.input.display(),
            report.output.display(),
            report.mode,
            report.points_in,
            s.moved,
            s.singular,
            s.degenerate_neighbourhoods,
            s.duplicates,
            report.dropped_non_finite,
            report.wall_s,
            report.cpu_s,
            report.peak_rss_bytes as f64 / (1024.0 * 1024.0),
        );
        if report.dropped_non_finite > 0 {
            eprintln!(
                "qemd: warning: {} points with NaN or infinite coordinates were dropped",
                report.dropped_non_finite
            );
        }
    }
    Ok(())
}
