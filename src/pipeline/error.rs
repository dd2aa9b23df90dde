//! The error of a pipeline run, and how the errors of the layers below map into it (their
//! cancellation is the run's).

use std::path::{Path, PathBuf};

use thiserror::Error;

use super::SpecError;
use crate::denoise::DenoiseError;
use crate::io::{self, IoError};
use crate::neighbours::NeighboursError;
use crate::tiling::TilingError;

/// Errors of a pipeline run; each names the file concerned.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// Reading or writing failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The parameters are invalid (checked before any I/O; the spec's one check).
    #[error(transparent)]
    Params(#[from] SpecError),
    /// The denoiser refused the input file `path`.
    #[error("{path}: {error}", path = .path.display())]
    Denoise {
        /// Input file.
        path: PathBuf,
        /// What the denoiser said.
        error: DenoiseError,
    },
    /// The output path names the input file.
    #[error("{path}: refusing to overwrite the input file", path = .path.display())]
    SameFile {
        /// The path given twice.
        path: PathBuf,
    },
    /// The temporary directory is unusable.
    #[error("{path}: temporary directory unusable: {detail}", path = .path.display())]
    TempDir {
        /// The directory.
        path: PathBuf,
        /// Why.
        detail: String,
    },
    /// The tiled path failed.
    #[error("{path}: {error}", path = .path.display())]
    Tiling {
        /// Input file.
        path: PathBuf,
        /// What failed.
        error: TilingError,
    },
    /// `--classes` was given for an input without a class field.
    #[error(
        "{path}: --classes needs a class field (a LAS classification, or a `class` or `label` \
         field), and this file has none",
        path = .path.display()
    )]
    NoClassField {
        /// Input file.
        path: PathBuf,
    },
    /// A mesh (which runs whole, in memory) needs more memory than the budget allows.
    #[error(
        "{path}: a mesh of {vertices} vertices and {faces} faces needs about {needed} in memory \
         (a mesh runs whole), more than the memory budget of {budget}; raise --memory-budget \
         (memory_budget in the service's configuration)",
        path = .path.display(),
        needed = bytesize::ByteSize(*.needed),
        budget = bytesize::ByteSize(*.budget)
    )]
    MeshBudget {
        /// Input file.
        path: PathBuf,
        /// Its vertices.
        vertices: u64,
        /// Its faces.
        faces: u64,
        /// Bytes it needs.
        needed: u64,
        /// The memory budget.
        budget: u64,
    },
    /// The run was cancelled (Ctrl-C, a job cancel).
    #[error("cancelled")]
    Cancelled,
    /// The report could not be written.
    #[error("{path}: cannot write report: {detail}", path = .path.display())]
    Report {
        /// Report path.
        path: PathBuf,
        /// What failed.
        detail: String,
    },
}

impl PipelineError {
    /// The error of the denoiser on `path`; its cancellation is the run's.
    pub(crate) fn denoise(path: &Path, error: DenoiseError) -> PipelineError {
        match error {
            DenoiseError::Neighbours(NeighboursError::Cancelled) => PipelineError::Cancelled,
            error => PipelineError::Denoise {
                path: path.to_path_buf(),
                error,
            },
        }
    }

    /// The error of the tiled path on `path`; its cancellation is the run's.
    pub(crate) fn tiling(path: &Path, error: TilingError) -> PipelineError {
        match error {
            TilingError::Cancelled
            | TilingError::Denoise {
                error: DenoiseError::Neighbours(NeighboursError::Cancelled),
                ..
            } => PipelineError::Cancelled,
            error => PipelineError::Tiling {
                path: path.to_path_buf(),
                error,
            },
        }
    }

    /// The same error naming the stream `input` where it named its spool.
    /// True when the input (its content) or the parameters caused the failure (a request larger
    /// than the memory budget included), false for the environment's failures (an OS error, the
    /// temporary directory, cancellation).
    pub fn is_input_fault(&self) -> bool {
        match self {
            PipelineError::Io(io) => !matches!(io, IoError::Io { .. }),
            PipelineError::Denoise { .. }
            | PipelineError::Params(_)
            | PipelineError::NoClassField { .. }
            | PipelineError::MeshBudget { .. } => true,
            // The request asks for more than the memory budget can hold (a larger k, a longer
            // reach): the request's to change, as a bad parameter is (issue 51: a sync request
            // answered 500).
            PipelineError::Tiling {
                error: TilingError::Budget { .. } | TilingError::PointBudget { .. },
                ..
            } => true,
            _ => false,
        }
    }

    /// The error with every mention of the path `from` replaced by `to` (a temporary file by the
    /// name the user knows).
    pub(crate) fn with_path(self, from: &Path, to: &Path) -> PipelineError {
        let swap = |p: PathBuf| if p == from { to.to_path_buf() } else { p };
        match self {
            PipelineError::Io(e) => PipelineError::Io(e.with_path(from, to)),
            PipelineError::Denoise { path, error } => PipelineError::Denoise {
                path: swap(path),
                error,
            },
            PipelineError::Tiling { path, error } => PipelineError::Tiling {
                path: swap(path),
                error,
            },
            PipelineError::SameFile { path } => PipelineError::SameFile { path: swap(path) },
            PipelineError::NoClassField { path } => {
                PipelineError::NoClassField { path: swap(path) }
            }
            PipelineError::MeshBudget {
                path,
                vertices,
                faces,
                needed,
                budget,
            } => PipelineError::MeshBudget {
                path: swap(path),
                vertices,
                faces,
                needed,
                budget,
            },
            PipelineError::Report { path, detail } => PipelineError::Report {
                path: swap(path),
                detail,
            },
            other => other,
        }
    }

    pub(crate) fn with_input(self, input: &io::InputFile) -> PipelineError {
        match self {
            PipelineError::Io(e) => PipelineError::Io(input.explain(e)),
            other => other.with_path(input.path(), input.shown()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue10_parameters_and_files_have_one_variant_each() {
        let bad = || DenoiseError::Param {
            name: "k",
            detail: "must be ≥ 2".into(),
        };
        let params = PipelineError::from(SpecError::from(bad()));
        let file = PipelineError::denoise(Path::new("/data/in.ply"), bad());
        assert!(matches!(params, PipelineError::Params(_)));
        assert_eq!(params.to_string(), bad().to_string());
        assert_eq!(file.to_string(), format!("/data/in.ply: {}", bad()));
        let cancelled = DenoiseError::Neighbours(NeighboursError::Cancelled);
        assert!(matches!(
            PipelineError::denoise(Path::new("x"), cancelled),
            PipelineError::Cancelled
        ));
        assert!(matches!(
            PipelineError::tiling(Path::new("x"), TilingError::Cancelled),
            PipelineError::Cancelled
        ));
    }
}
