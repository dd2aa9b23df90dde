//! Prototype measurements behind the out-of-core design of issue 48 (docs/DECISIONS.md, "Out of
//! core at the cost of in memory"): for one cloud, the memory a streaming sweep would hold and
//! the bytes a spill of k-NN lists would take.
//!
//! ```sh
//! cargo run --release --example sweep_model -- FILE [--axis x|y|z|longest]
//! ```
//!
//! The cloud is read whole, its capped k-NN lists computed as the operator computes them, and
//! the default operator run once for its classes. Then, for a sweep along one axis:
//! - each point's list is known once the front has passed `x + ρ` (`ρ` its list's radius, the
//!   isolation radius for a capped list);
//! - each of the operator's hop passes (classes, filter iterations, updates, gains: `reach + 1`
//!   after the lists) is done at a point once the pass before is done at every list member; a
//!   point whose class does not move is done with everything once its class is (`--no-settle`
//!   turns that off);
//! - a point is held from the moment it is read until the last pass that reads it is done.
//!
//! Printed: the most points held at once by a window of one contiguous range (from the oldest
//! point still needed to the front), and by one that keeps only the points still needed; both
//! as a share of the cloud and in typical radii of sweep width. For the other candidate, the
//! bytes of the capped lists written once (raw `u32` members, and delta-coded varints in the
//! run's spatial order).

use std::path::PathBuf;

use glam::DVec3;
use qem_denoise::denoise::cloud::{reach, run_all};
use qem_denoise::denoise::{Params, isolation, origin_of};
use qem_denoise::io::Cloud;
use qem_denoise::neighbours::{KnnIndex, spatial_order};

fn main() -> anyhow::Result<()> {
    let mut file = None;
    let mut axis_arg = "longest".to_string();
    let mut settle = true;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--axis" => axis_arg = args.next().unwrap_or_default(),
            "--no-settle" => settle = false,
            _ => file = Some(PathBuf::from(a)),
        }
    }
    let file = file.ok_or_else(|| anyhow::anyhow!("a file"))?;
    let cloud = Cloud::read(&file, None)?;
    let pts: Vec<DVec3> = cloud
        .positions
        .iter()
        .copied()
        .filter(|p| qem_denoise::points::in_range(*p))
        .collect();
    let n = pts.len();
    let params = Params::default();
    let k = params.k();
    let ties: Vec<u64> = (0..n as u64).collect();
    let origin = origin_of(&pts);
    let iso = isolation::of_cloud(&pts, &ties, origin, k);
    let r_k = iso.map(|r| r / 32.0).unwrap_or(0.0);
    let index = KnnIndex::build(&pts, origin)?;
    let (lists, radii) = index.knn_all(k)?;
    let (lists, radii, _) = isolation::cap_lists(lists, radii, iso, |i, u| index.dist2(i, u));
    let result = run_all(&pts, &params)?;
    let classes = result.structure.clone().unwrap_or_default();
    let settled: Vec<bool> = (0..n)
        .map(|i| settle && classes.get(i).is_some_and(|&c| c >= 3))
        .collect();

    let bb = qem_denoise::points::Aabb::from_points(&pts);
    let ext = bb.max - bb.min;
    let axis = match axis_arg.as_str() {
        "x" => 0,
        "y" => 1,
        "z" => 2,
        _ => {
            if ext.x >= ext.y && ext.x >= ext.z {
                0
            } else if ext.y >= ext.z {
                1
            } else {
                2
            }
        }
    };
    let x: Vec<f64> = pts.iter().map(|p| p[axis]).collect();
    // Passes after the lists: the fits read the lists' own members' positions (done with the
    // list), then `reach + 1` hops (classes … the last update).
    let hops = reach(&params) + 1;
    // The class pass is hop 1.
    let class_hop = 1;
    let mut t: Vec<f64> = (0..n).map(|i| x[i] + radii[i].sqrt()).collect();
    // `times[h][i]`: the front position at which hop `h` is done at `i`.
    let mut times = vec![t.clone()];
    for h in 1..=hops {
        let prev = &times[h - 1];
        let next: Vec<f64> = (0..n)
            .map(|i| {
                if h > class_hop && settled[i] {
                    return times[class_hop][i];
                }
                let mut m = prev[i];
                for &u in lists.get(i) {
                    let u = u as usize;
                    // A settled member's later values are fixed once its class is.
                    let tu = if h - 1 > class_hop && settled[u] {
                        times[class_hop][u]
                    } else {
                        prev[u]
                    };
                    m = m.max(tu);
                }
                m
            })
            .collect();
        times.push(next);
    }
    t.clone_from(&times[hops]);
    // A point is needed until it is done and until every point listing it has done the passes
    // that read it (the last one, at most).
    let mut retire = t.clone();
    for i in 0..n {
        let last = if settled[i] {
            times[class_hop + 1][i]
        } else {
            t[i]
        };
        for &u in lists.get(i) {
            let u = u as usize;
            retire[u] = retire[u].max(last);
        }
        retire[i] = retire[i].max(last);
    }
    // Sweep the front over the points in axis order.
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| x[a].total_cmp(&x[b]));
    let mut by_retire: Vec<usize> = (0..n).collect();
    by_retire.sort_by(|&a, &b| retire[a].total_cmp(&retire[b]));
    // Events: read at x, retired at retire. Held = read − retired. Contiguous: from the oldest
    // (lowest x) point not retired to the front.
    let (mut held, mut peak_held) = (0i64, 0i64);
    let mut j = 0usize;
    let mut peak_contig = 0usize;
    let mut peak_width = 0.0f64;
    // Oldest not-retired point in axis order: a pointer that only moves forward while points at
    // it are retired.
    let mut rank = vec![0usize; n];
    for (r, &i) in order.iter().enumerate() {
        rank[i] = r;
    }
    let mut retired = vec![false; n];
    let mut oldest = 0usize;
    let step = (n / 2000).max(1);
    for (r, &i) in order.iter().enumerate() {
        let front = x[i];
        held += 1;
        while j < n && retire[by_retire[j]] <= front {
            retired[by_retire[j]] = true;
            held -= 1;
            j += 1;
        }
        if r % step == 0 || r + 1 == n {
            while oldest < r && retired[order[oldest]] {
                oldest += 1;
            }
            peak_held = peak_held.max(held);
            if r + 1 - oldest > peak_contig {
                peak_contig = r + 1 - oldest;
                peak_width = front - x[order[oldest]];
            }
        }
    }
    let _ = rank;
    // Retention with a lister horizon: a point is kept while a point not read yet could list
    // it (x_u ≥ H(front), H the least x_j − ρ_j over the points ahead) or while it is needed.
    // `heavy`: only listers that are not isolated count (isolated ones read positions only).
    let isolated_pt =
        |i: usize| iso.is_some_and(|r| radii[i] >= r * r * (1.0 - 1e-12)) && lists.get(i).len() < k;
    for heavy in [false, true] {
        let mut suffix = vec![f64::INFINITY; n + 1];
        for r in (0..n).rev() {
            let i = order[r];
            let h = if heavy && isolated_pt(i) {
                f64::INFINITY
            } else {
                x[i] - radii[i].sqrt()
            };
            suffix[r] = suffix[r + 1].min(h);
        }
        let mut peak = 0usize;
        let samples = 300usize;
        for sidx in 0..samples {
            let r = (n - 1) * sidx / (samples - 1);
            let front = x[order[r]];
            let h = suffix[r + 1];
            let mut c = 0usize;
            for &i in &order[..=r] {
                if x[i] >= h || retire[i] > front {
                    c += 1;
                }
            }
            peak = peak.max(c);
        }
        println!(
            "held with a lister horizon ({}): peak {peak} ({:.4} of the cloud)",
            if heavy {
                "listers not isolated"
            } else {
                "every lister"
            },
            peak as f64 / n as f64
        );
    }
    let lag: Vec<f64> = (0..n).map(|i| t[i] - x[i]).collect();
    let mut sorted = lag.clone();
    sorted.sort_by(f64::total_cmp);
    let q = |f: f64| sorted[((n - 1) as f64 * f) as usize] / r_k.max(f64::MIN_POSITIVE);
    println!("file\t{}", file.display());
    println!("points\t{n}");
    println!(
        "extent\t{:.4} {:.4} {:.4} (axis {axis})",
        ext.x, ext.y, ext.z
    );
    println!("r_k\t{r_k:.6}\tisolation\t{:.6}", iso.unwrap_or(0.0));
    println!(
        "extent along the axis in r_k\t{:.0}",
        ext[axis] / r_k.max(f64::MIN_POSITIVE)
    );
    println!(
        "settled share\t{:.3}",
        settled.iter().filter(|&&s| s).count() as f64 / n as f64
    );
    println!(
        "lag to done (r_k): p50 {:.2} p99 {:.2} p99.9 {:.2} max {:.2}",
        q(0.5),
        q(0.99),
        q(0.999),
        q(1.0)
    );
    println!(
        "held, only needed points: peak {peak_held} ({:.4} of the cloud)",
        peak_held as f64 / n as f64
    );
    println!(
        "held, one contiguous range: peak {peak_contig} ({:.4} of the cloud, {:.1} r_k wide)",
        peak_contig as f64 / n as f64,
        peak_width / r_k.max(f64::MIN_POSITIVE)
    );
    // List radii by kind, in r_k.
    let isolated =
        |i: usize| radii[i] >= iso.map_or(f64::INFINITY, |r| r * r) && lists.get(i).len() < k;
    let mut kinds: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    for i in 0..n {
        let kind = if isolated(i) {
            0
        } else if settled[i] {
            1
        } else {
            2
        };
        kinds[kind].push(radii[i].sqrt() / r_k);
    }
    for (name, mut v) in ["isolated", "settled", "moving"].into_iter().zip(kinds) {
        if v.is_empty() {
            println!("rho {name}: none");
            continue;
        }
        v.sort_by(f64::total_cmp);
        let m = v.len();
        let at = |f: f64| v[((m - 1) as f64 * f) as usize];
        println!(
            "rho {name} ({m}): p50 {:.2} p99 {:.2} p99.9 {:.2} p99.99 {:.2} max {:.2}",
            at(0.5),
            at(0.99),
            at(0.999),
            at(0.9999),
            at(1.0)
        );
    }
    // Candidate B: the lists spilled once.
    let order = spatial_order(&pts);
    let mut inv = vec![0u32; n];
    for (j, &i) in order.iter().enumerate() {
        inv[i as usize] = j as u32;
    }
    let mut varint = 0u64;
    for (j, &i) in order.iter().enumerate() {
        for &u in lists.get(i as usize) {
            let d = inv[u as usize] as i64 - j as i64;
            let z = ((d << 1) ^ (d >> 63)) as u64;
            varint += u64::from((64 - z.leading_zeros()).max(1).div_ceil(7));
        }
    }
    println!(
        "lists spilled: raw {:.1} B/pt, varint deltas in Morton order {:.1} B/pt",
        (lists.indices.len() * 4) as f64 / n as f64,
        varint as f64 / n as f64
    );
    Ok(())
}
