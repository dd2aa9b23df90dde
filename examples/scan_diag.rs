//! Where the default point operator adds error on a real scan with known noise: per class of the
//! clean scan (its LAS class, or its structure class), the RMS ratio, and how much of the excess
//! error comes from each class the operator itself found on the noisy scan.
//!
//! ```sh
//! cargo run --release --example scan_diag -- CLEAN NOISY [--flag value]...
//! ```
//!
//! CLEAN and NOISY are the protocol's files (`benches/real_scans.py` keeps them in its work
//! directory). Extra `--knn`, `--filter`, `--updates` set those parameters. Prints one table.

use std::path::PathBuf;

use qem_denoise::denoise::Params;
use qem_denoise::denoise::cloud::run_all;
use qem_denoise::denoise::structure::Structure;
use qem_denoise::eval::scans::{classes_of, noise_removed};
use qem_denoise::io::Cloud;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let clean_path = PathBuf::from(args.next().unwrap_or_default());
    let noisy_path = PathBuf::from(args.next().unwrap_or_default());
    let mut params = Params::default();
    while let Some(a) = args.next() {
        let v = args.next().unwrap_or_default();
        match a.as_str() {
            "--knn" => params.knn = Some(v.parse()?),
            "--filter" => params.filter = Some(v.parse()?),
            "--updates" => params.updates = Some(v.parse()?),
            _ => anyhow::bail!("unknown flag {a}"),
        }
    }
    let clean = Cloud::read(&clean_path, None)?;
    let noisy = Cloud::read(&noisy_path, None)?;
    let classes = classes_of(&clean)?;
    let r = run_all(&noisy.positions, &params)?;
    let mut out = noisy.clone();
    out.positions.clone_from(&r.positions);
    let nr = noise_removed(&clean, &noisy, &out, &classes)?;
    let run = r.structure.unwrap_or_default();
    if let Ok(path) = std::env::var("DIAG_DUMP") {
        use std::io::Write;
        let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
        writeln!(f, "i,cls,run,cx,cy,cz,nx,ny,nz,ox,oy,oz")?;
        for i in 0..clean.positions.len() {
            let (c, n, o) = (clean.positions[i], noisy.positions[i], out.positions[i]);
            writeln!(
                f,
                "{i},{},{},{},{},{},{},{},{},{},{},{}",
                classes.codes[i],
                run.get(i).copied().unwrap_or(5),
                c.x,
                c.y,
                c.z,
                n.x,
                n.y,
                n.z,
                o.x,
                o.y,
                o.z
            )?;
        }
    }
    println!(
        "{}: planar {:.3} ({} pts)",
        noisy_path.display(),
        nr.planar.ratio,
        nr.planar.count
    );
    for row in &nr.rows {
        if row.class == u32::MAX {
            println!("  all: ratio {:.3} ({} pts)", row.ratio, row.count);
            continue;
        }
        // Excess squared error per run class: Σ |out − clean|² − |noisy − clean|².
        let mut excess = [0.0f64; 6];
        let mut count = [0usize; 6];
        let mut noisy2 = 0.0;
        for i in 0..clean.positions.len() {
            if classes.codes[i] != row.class || !clean.positions[i].is_finite() {
                continue;
            }
            let c = clean.positions[i];
            let e0 = (noisy.positions[i] - c).length_squared();
            let e1 = (out.positions[i] - c).length_squared();
            noisy2 += e0;
            let s = run.get(i).copied().unwrap_or(5) as usize;
            excess[s] += e1 - e0;
            count[s] += 1;
        }
        let parts: Vec<String> = Structure::ALL
            .iter()
            .filter(|s| count[**s as usize] > 0)
            .map(|s| {
                let k = *s as usize;
                format!(
                    "{} {}: {:+.3}",
                    s.name(),
                    count[k],
                    excess[k] / noisy2.max(f64::MIN_POSITIVE)
                )
            })
            .collect();
        let flag = if row.ratio > 1.0 { "  <--" } else { "" };
        println!(
            "  {} ({} pts): ratio {:.3}{flag}   [{}]",
            row.name,
            row.count,
            row.ratio,
            parts.join(", ")
        );
    }
    Ok(())
}
