//! What clients ask the service for and what it answers (request and answer types), and the
//! checks of a request that need no input file: formats by name, the spec's errors as request
//! fields, output options a sink would refuse.

use std::path::PathBuf;

use super::JobsError;
use super::progress::ProgressView;
use super::store::JobRow;
use crate::io::Format;
use crate::pipeline::{DenoiseSpec, OutlierMode, Report, SpecError, SpecOverlay};

/// How the client named the format of an upload.
#[derive(Debug, Clone, Default)]
pub struct FormatHint {
    /// `?format=` (a format name or extension).
    pub format: Option<String>,
    /// The client's file name (its extension is a hint too).
    pub filename: Option<String>,
}

/// A job submission, as the API received it (validated here).
#[derive(Debug, Clone)]
pub struct JobRequest {
    /// The input upload's id.
    pub input: String,
    /// The request's parameter choices (resolved and validated here, over the configured
    /// outlier threshold).
    pub spec: SpecOverlay,
    /// Output format (else the input's).
    pub output_format: Option<Format>,
}

/// A synchronous request.
#[derive(Debug, Clone)]
pub struct SyncRequest {
    /// Input format.
    pub format: Format,
    /// The request's parameter choices.
    pub spec: SpecOverlay,
    /// Output format (else the input's).
    pub output_format: Option<Format>,
}

/// The answer of a synchronous request.
#[derive(Debug, Clone)]
pub struct SyncOutput {
    /// The denoised file.
    pub bytes: Vec<u8>,
    /// Its format.
    pub format: Format,
    /// What the run did (paths replaced by `input` and `result`).
    pub report: Report,
    /// True when the run needed a temporary file (a body above the memory budget, E57 or COPC
    /// output); otherwise nothing touched the disk.
    pub spooled: bool,
}

/// A job with its live progress.
#[derive(Debug, Clone)]
pub struct JobInfo {
    /// The stored row.
    pub row: JobRow,
    /// Progress: live while running, complete when successful, `None` otherwise.
    pub progress: Option<ProgressView>,
}

/// A downloadable result.
#[derive(Debug, Clone)]
pub struct ResultFile {
    /// Where it is.
    pub path: PathBuf,
    /// Bytes.
    pub size: u64,
    /// SHA-256 (hex): the strong ETag.
    pub sha256: String,
    /// Format.
    pub format: Format,
    /// The name it downloads under ([`super::store::JobSpec::result_filename`]).
    pub filename: String,
    /// When the job finished, ms since the Unix epoch.
    pub finished_ms: i64,
}

/// The canonical extension for a format name (`kitti` → `bin`, `txt` → `xyz`), `None` when
/// unknown.
pub fn canonical_format(name: &str) -> Option<String> {
    Format::from_name(name.trim()).map(|f| f.name().to_string())
}

/// The pipeline's format for an extension the service produced (always known).
pub(super) fn format_of(ext: &str) -> Result<Format, JobsError> {
    Format::from_name(ext).ok_or_else(|| JobsError::Internal(format!("unknown extension {ext}")))
}

/// Maps a spec error to the request field it names (`params.knn`; the outlier options may sit
/// at the top level of a job, so they keep their bare names).
pub(super) fn spec_error(e: SpecError) -> JobsError {
    JobsError::Invalid {
        field: match e.field {
            f @ ("outliers" | "outlier_alpha") => f.to_string(),
            f => format!("params.{f}"),
        },
        detail: e.detail,
    }
}

/// Refuses output options a sink would refuse later (noise flags and written normals in KITTI,
/// raw `.bin`, OBJ, OFF).
pub(super) fn validate_output(spec: &DenoiseSpec, f: Format) -> Result<(), JobsError> {
    let output = f.name();
    if spec.params.write_normals
        && let Some(why) = crate::io::refuse_normals(f)
    {
        return Err(JobsError::Invalid {
            field: "params.write_normals".into(),
            detail: format!("output format {output}: {why}"),
        });
    }
    if spec.outliers == OutlierMode::Classify
        && matches!(
            f,
            Format::Kitti | Format::Nuscenes | Format::Bin(_) | Format::Obj | Format::Off
        )
    {
        return Err(JobsError::Invalid {
            field: "outliers".into(),
            detail: format!(
                "`classify` needs an output format with room for a flag; {output} has none \
                 (use remove, or another output_format)"
            ),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parameter_errors_name_fields() {
        let resolve = |o: SpecOverlay| o.resolve(2.0).map_err(spec_error);
        match resolve(SpecOverlay {
            knn: Some(1),
            ..SpecOverlay::default()
        }) {
            Err(JobsError::Invalid { field, .. }) => assert_eq!(field, "params.knn"),
            other => panic!("{other:?}"),
        }
        match resolve(SpecOverlay {
            outlier_alpha: Some(-1.0),
            ..SpecOverlay::default()
        }) {
            Err(JobsError::Invalid { field, .. }) => assert_eq!(field, "outlier_alpha"),
            other => panic!("{other:?}"),
        }
        let spec = |outliers, write_normals| {
            let mut s = DenoiseSpec {
                outliers,
                ..DenoiseSpec::default()
            };
            s.params.write_normals = write_normals;
            s
        };
        assert!(validate_output(&spec(OutlierMode::Classify, false), Format::Kitti).is_err());
        assert!(validate_output(&spec(OutlierMode::Remove, false), Format::Kitti).is_ok());
        match validate_output(&spec(OutlierMode::Off, true), Format::Obj) {
            Err(JobsError::Invalid { field, detail }) => {
                assert_eq!(field, "params.write_normals");
                assert!(detail.starts_with("output format obj: "), "{detail}");
            }
            other => panic!("{other:?}"),
        }
        assert!(validate_output(&spec(OutlierMode::Off, true), Format::Las).is_ok());
    }
}
