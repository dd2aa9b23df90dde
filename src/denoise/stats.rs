//! Run statistics and per-phase timing.

use std::time::Instant;

use cpu_time::ProcessTime;

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

/// What a denoising run did. Per-pass counters are summed over passes.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Stats {
    /// Points (or vertices) in the input.
    pub points: u64,
    /// Point moves performed (summed over passes).
    pub moved: u64,
    /// Points left in place because the summed quadric was singular or the solve not finite.
    pub singular: u64,
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
    /// Largest displacement of any point in any pass.
    pub max_step: f64,
    /// Timing per phase, in the order phases first ran.
    pub phases: Vec<PhaseTiming>,
}

impl Stats {
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
