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
    /// Largest distance between a point's input and output positions.
    pub max_step: f64,
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
        }
    }

    /// Adds another run's counters and phase timings (tiles of one job).
    pub fn merge(&mut self, o: &Stats) {
        self.points += o.points;
        self.moved += o.moved;
        self.singular += o.singular;
        self.far += o.far;
        self.unreferenced += o.unreferenced;
        self.zero_area_faces += o.zero_area_faces;
        self.degenerate_neighbourhoods += o.degenerate_neighbourhoods;
        self.duplicates += o.duplicates;
        self.non_finite += o.non_finite;
        self.max_step = self.max_step.max(o.max_step);
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
