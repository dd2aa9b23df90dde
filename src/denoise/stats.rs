//! Run statistics and per-phase timing.

use std::time::Instant;

use cpu_time::ProcessTime;
use glam::DVec3;

/// Wall and CPU time of one phase (summed over iterations).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PhaseTiming {
    /// Phase name (`neighbours`, `normals`, `solve`, `read`, `write`, …).
    pub name: String,
    /// Elapsed wall-clock seconds.
    pub wall_s: f64,
    /// Process CPU seconds (all threads) spent during the phase.
    pub cpu_s: f64,
}

/// What a denoising run did. Every counter counts points (or vertices), once each.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Stats {
    /// Points (or vertices) in the input.
    pub points: u64,
    /// Points whose final position differs from their input position.
    pub moved: u64,
    /// Points left in place in at least one pass because the summed quadric was singular or the
    /// solve not finite.
    pub singular: u64,
    /// Points left in place in at least one pass because the minimiser lay farther than their
    /// neighbourhood reaches (isolated points, outliers; not checked by the paper's plain solve).
    #[serde(default)]
    pub far: u64,
    /// Mesh vertices that no face references (they never move).
    pub unreferenced: u64,
    /// Faces with zero area (they contribute no normal).
    pub zero_area_faces: u64,
    /// Points whose neighbourhood is coincident or collinear (no plane; no quadric of their own).
    pub degenerate_neighbourhoods: u64,
    /// Points at exactly the position of a lower-indexed point.
    pub duplicates: u64,
    /// Non-finite points, excluded from processing.
    pub non_finite: u64,
    /// Points whose displacement was clamped to the bound of their local noise or `--max-move`.
    #[serde(default)]
    pub bounded: u64,
    /// Points with fewer than k points within the isolation radius, kept in place.
    #[serde(default)]
    pub isolated: u64,
    /// Points kept in place for their class: classes `--classes` does not name, and on LAS input
    /// the noise classes 7 and 18 (unless named) and withheld points.
    #[serde(default)]
    pub held: u64,
    /// Largest distance between a point's input and output positions.
    pub max_step: f64,
    /// The guarded operator's estimate of the scan's noise, in the input's units
    /// ([`crate::denoise::cloud::Globals::noise`]: along the beams where they are known): every
    /// step is bounded by a few times it, so a scan read as noise-free does not move. `None` for
    /// the other operators.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_estimate: Option<f64>,
    /// Points per neighbourhood class (point clouds with the guarded operator).
    #[serde(default)]
    pub structure: StructureCounts,
    /// The distribution of displacements, in the input's units.
    #[serde(default)]
    pub displacement: Displacements,
    /// Timing per phase, in the order phases first ran.
    pub phases: Vec<PhaseTiming>,
}

impl Stats {
    /// Counts moves, singular stays and the largest displacement over the points `counted` says.
    pub fn book_moves(
        &mut self,
        before: &[DVec3],
        after: &[DVec3],
        stayed: &[u8],
        counted: impl Fn(usize) -> bool,
    ) {
        for i in (0..before.len()).filter(|&i| counted(i)) {
            let step = (after[i] - before[i]).length();
            if step > 0.0 {
                self.moved += 1;
                self.max_step = self.max_step.max(step);
            }
            self.singular += (stayed[i] & 1 != 0) as u64;
            self.far += (stayed[i] & 2 != 0) as u64;
            self.bounded += (stayed[i] & 4 != 0) as u64;
            self.isolated += (stayed[i] & 8 != 0) as u64;
            self.held += (stayed[i] & super::common::stay::HELD != 0) as u64;
            self.displacement.add(step);
        }
        self.displacement.refresh();
    }

    /// Adds another run's counters and phase timings (tiles of one job).
    pub fn merge(&mut self, o: &Stats) {
        self.points += o.points;
        self.moved += o.moved;
        self.singular += o.singular;
        self.far += o.far;
        self.bounded += o.bounded;
        self.isolated += o.isolated;
        self.held += o.held;
        self.structure.merge(&o.structure);
        self.displacement.merge(&o.displacement);
        self.unreferenced += o.unreferenced;
        self.zero_area_faces += o.zero_area_faces;
        self.degenerate_neighbourhoods += o.degenerate_neighbourhoods;
        self.duplicates += o.duplicates;
        self.non_finite += o.non_finite;
        self.max_step = self.max_step.max(o.max_step);
        // Every tile reads the same global estimate.
        self.noise_estimate = self.noise_estimate.or(o.noise_estimate);
        for p in &o.phases {
            self.add_phase(&p.name, p.wall_s, p.cpu_s);
        }
    }

    /// Adds `wall_s` and `cpu_s` to phase `name`, creating it on first use.
    pub fn add_phase(&mut self, name: &str, wall_s: f64, cpu_s: f64) {
        if let Some(p) = self.phases.iter_mut().find(|p| p.name == name) {
            p.wall_s += wall_s;
            p.cpu_s += cpu_s;
        } else {
            self.phases.push(PhaseTiming {
                name: name.to_string(),
                wall_s,
                cpu_s,
            });
        }
    }
}

/// Points per neighbourhood class ([`super::structure::Structure`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct StructureCounts {
    /// Surfaces.
    pub surface: u64,
    /// Creases and corners.
    pub edge: u64,
    /// Lines (wires, poles, scan rings).
    pub line: u64,
    /// Volumetric scatter (left in place).
    pub scatter: u64,
    /// Isolated points (left in place).
    pub sparse: u64,
    /// Coincident neighbourhoods (left in place).
    pub degenerate: u64,
}

impl StructureCounts {
    /// Counts from per-class totals indexed by class code.
    pub fn from_codes(c: [u64; 6]) -> StructureCounts {
        StructureCounts {
            surface: c[0],
            edge: c[1],
            line: c[2],
            scatter: c[3],
            sparse: c[4],
            degenerate: c[5],
        }
    }

    /// Adds another run's counts.
    pub fn merge(&mut self, o: &StructureCounts) {
        self.surface += o.surface;
        self.edge += o.edge;
        self.line += o.line;
        self.scatter += o.scatter;
        self.sparse += o.sparse;
        self.degenerate += o.degenerate;
    }
}

/// Relative width of a displacement histogram bin (2 %).
const BIN_RATIO: f64 = 1.02;
/// Lower edge of the first non-zero bin: displacements below it share bin 1.
const BIN_FLOOR: f64 = 1e-9;

/// The distribution of displacements as a histogram with bins 2 % wide (bin 0: no move), so runs
/// and tiles merge exactly; quantiles are read as a bin's upper edge (within 2 % above the true
/// value), the maximum is exact.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Displacements {
    /// Points counted.
    pub count: u64,
    /// Median displacement (upper bin edge).
    pub p50: f64,
    /// 99th percentile (upper bin edge).
    pub p99: f64,
    /// Largest displacement.
    pub max: f64,
    /// Non-empty bins as `[bin, count]`, ascending.
    pub bins: Vec<[u64; 2]>,
}

impl Displacements {
    fn bin_of(d: f64) -> u64 {
        if d <= 0.0 || d.is_nan() {
            0
        } else if d <= BIN_FLOOR {
            1
        } else {
            // `libm::log`, the same bits on every platform: the global noise is a bin edge.
            2 + (libm::log(d / BIN_FLOOR) / libm::log(BIN_RATIO))
                .floor()
                .min(1e6) as u64
        }
    }

    fn upper_edge(bin: u64) -> f64 {
        match bin {
            0 => 0.0,
            1 => BIN_FLOOR,
            b => BIN_FLOOR * BIN_RATIO.powi((b - 1) as i32),
        }
    }

    /// Counts one displacement.
    pub fn add(&mut self, d: f64) {
        let b = Self::bin_of(d);
        match self.bins.binary_search_by_key(&b, |e| e[0]) {
            Ok(k) => self.bins[k][1] += 1,
            Err(k) => self.bins.insert(k, [b, 1]),
        }
        self.count += 1;
        self.max = self.max.max(d);
    }

    /// Adds another run's displacements.
    pub fn merge(&mut self, o: &Displacements) {
        for &[b, c] in &o.bins {
            match self.bins.binary_search_by_key(&b, |e| e[0]) {
                Ok(k) => self.bins[k][1] += c,
                Err(k) => self.bins.insert(k, [b, c]),
            }
        }
        self.count += o.count;
        self.max = self.max.max(o.max);
        self.refresh();
    }

    /// The `q` quantile (upper bin edge, capped by the maximum).
    pub fn quantile(&self, q: f64) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let rank = ((q * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0;
        for &[b, c] in &self.bins {
            seen += c;
            if seen >= rank {
                return Self::upper_edge(b).min(self.max);
            }
        }
        self.max
    }

    /// Recomputes `p50` and `p99` from the bins (after [`Displacements::add`]).
    pub fn refresh(&mut self) {
        self.p50 = self.quantile(0.5);
        self.p99 = self.quantile(0.99);
    }
}

/// Measures consecutive phases: each [`Timer::lap`] books the time since the previous one.
#[derive(Debug)]
pub struct Timer {
    wall: Instant,
    cpu: ProcessTime,
}

impl Default for Timer {
    fn default() -> Self {
        Timer::start()
    }
}

impl Timer {
    /// Starts timing now.
    pub fn start() -> Timer {
        Timer {
            wall: Instant::now(),
            cpu: ProcessTime::now(),
        }
    }

    /// Books the time since the last lap to phase `name` and restarts.
    pub fn lap(&mut self, name: &str, stats: &mut Stats) {
        let wall = self.wall.elapsed().as_secs_f64();
        let cpu = self.cpu.elapsed().as_secs_f64();
        stats.add_phase(name, wall, cpu);
        *self = Timer::start();
    }
}
