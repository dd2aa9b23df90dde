//! A job: where it reads and writes, and its [`DenoiseSpec`] (the parameters and the outlier
//! handling).

use std::path::PathBuf;

use super::DenoiseSpec;
use crate::io::Format;

/// What to do with statistical outliers: points whose mean distance to their k-NN list is above
/// `mean + alpha·σ` of that statistic over the whole cloud.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum OutlierMode {
    /// Leave them.
    #[default]
    Off,
    /// Flag them: LAS class 7, or a `noise` property.
    Classify,
    /// Drop them from the output.
    Remove,
}

/// Where a job reads and writes, and what it does.
#[derive(Debug, Clone)]
pub struct Job {
    /// Input file.
    pub input: PathBuf,
    /// Output file.
    pub output: PathBuf,
    /// Input format (else from the extension).
    pub input_format: Option<Format>,
    /// Output format (else from the extension).
    pub output_format: Option<Format>,
    /// What the run computes.
    pub spec: DenoiseSpec,
    /// Point clouds: the sensor's trajectory (`--trajectory`, [`crate::io::trajectory`]): each
    /// return's beam runs from the position at its time.
    pub trajectory: Option<PathBuf>,
}

impl Job {
    /// A job with the default spec (no outlier handling).
    pub fn new(input: impl Into<PathBuf>, output: impl Into<PathBuf>) -> Job {
        Job {
            input: input.into(),
            output: output.into(),
            input_format: None,
            output_format: None,
            spec: DenoiseSpec::default(),
            trajectory: None,
        }
    }
}
