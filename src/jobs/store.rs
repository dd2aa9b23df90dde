//! The job store: uploads and jobs in one SQLite file (`rusqlite`, bundled SQLite).
//!
//! ```text
//!  uploads  id · tenant · created · complete · length (declared, resumable) · size (received)
//!           · sha256 · format (extension) · filename · hint (declared format) · points · faces
//!  jobs     seq (order) · id · tenant · upload · status · spec (JSON) · created · started
//!           · finished · report (JSON) · error · result_size · result_sha256
//!           · slurm (JSON: the SLURM jobs submitted for it, executor = "slurm")
//! ```
//!
//! Every method is synchronous and short; the async service calls them on the blocking pool
//! ([`super::bridge::blocking`]). One connection sits behind a std `Mutex`: SQLite serialises
//! writers anyway, and a lock is never held across an `.await`. The database runs in WAL mode with
//! `synchronous = NORMAL`: a committed transaction survives the process being killed.
//!
//! Lookups that take a tenant filter by it, so a tenant can never read another tenant's rows;
//! `None` (recovery, workers) sees every row.

use std::path::Path;
use std::sync::Mutex;

use rusqlite::{Connection, OptionalExtension, Row, params};

use super::JobsError;
use super::slurm::SlurmRecord;
use crate::io::Format;
use crate::pipeline::scaleout::Executor;
use crate::pipeline::{DenoiseSpec, Report};

/// The status of a job, as OGC API – Processes names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Queued, waiting for a slot.
    Accepted,
    /// Running.
    Running,
    /// Finished; the result can be downloaded.
    Successful,
    /// Finished with an error.
    Failed,
    /// Cancelled or deleted by its owner; its files are gone.
    Dismissed,
}

impl Status {
    /// Every status, in lifecycle order.
    pub const ALL: [Status; 5] = [
        Status::Accepted,
        Status::Running,
        Status::Successful,
        Status::Failed,
        Status::Dismissed,
    ];

    /// The name used on the wire and in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Accepted => "accepted",
            Status::Running => "running",
            Status::Successful => "successful",
            Status::Failed => "failed",
            Status::Dismissed => "dismissed",
        }
    }

    /// Parses a status name.
    pub fn parse(s: &str) -> Option<Status> {
        Status::ALL.into_iter().find(|x| x.as_str() == s)
    }
}

/// An upload: a file received whole or in resumable chunks.
#[derive(Debug, Clone, PartialEq)]
pub struct Upload {
    /// Random id (UUID v4).
    pub id: String,
    /// Owner.
    pub tenant: String,
    /// Creation time, ms since the Unix epoch.
    pub created_ms: i64,
    /// All bytes received and the content validated.
    pub complete: bool,
    /// Declared total length of a resumable upload.
    pub length: Option<u64>,
    /// Bytes received.
    pub size: u64,
    /// SHA-256 of the content (hex), once complete.
    pub sha256: Option<String>,
    /// The format, once complete (stored as its name: `ply`, `laz`, …).
    pub format: Option<Format>,
    /// The client's file name, when given.
    pub filename: Option<String>,
    /// The format the client declared (`?format=`), applied on completion.
    pub hint: Option<String>,
    /// Points the header declares, once complete.
    pub points: Option<u64>,
    /// Faces the header declares (meshes), once complete.
    pub faces: Option<u64>,
}

/// What a job computes: the validated request, frozen at submission so that a restarted server
/// (even with another configuration) resumes the same plan.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct JobSpec {
    /// What the run computes (stored flat, as `params`, `outliers` and `outlier_alpha`).
    #[serde(flatten)]
    pub denoise: DenoiseSpec,
    /// Output format (stored as its name: `ply`, `las`, `laz`, …).
    pub output_format: Format,
    /// Memory budget of the run.
    pub memory_budget: u64,
    /// Forced tile size (large clouds), `None` to let the memory budget decide.
    pub tile_points: Option<u64>,
    /// Where it runs (chosen at submission; rows of earlier versions are local).
    #[serde(default)]
    pub executor: Executor,
    /// The input upload's file name, when the client gave one (the result downloads as
    /// `<stem>.denoised.<ext>`; rows of earlier versions have none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_filename: Option<String>,
}

impl JobSpec {
    /// The name the result downloads under: the input's file name with `.denoised` and the
    /// output format's extension in place of its own (`scan.laz` → `scan.denoised.laz`,
    /// `site.copc.laz` → `site.denoised.copc.laz`), else `<id>.<ext>`.
    pub fn result_filename(&self, id: &str) -> String {
        let ext = self.output_format.name();
        let Some(name) = self.input_filename.as_deref() else {
            return format!("{id}.{ext}");
        };
        // The last path component (a browser may send a path), without its format extension.
        let name = name.rsplit(['/', '\\']).next().unwrap_or(name);
        let lower = name.to_ascii_lowercase();
        let stem_len = [".copc.laz", ".pcd.bin"]
            .iter()
            .find(|e| lower.ends_with(*e))
            .map(|e| name.len() - e.len())
            .or_else(|| name.rfind('.'))
            .unwrap_or(name.len());
        let stem = &name[..stem_len];
        if stem.is_empty() {
            format!("{id}.{ext}")
        } else {
            format!("{stem}.denoised.{ext}")
        }
    }
}

/// A job row.
#[derive(Debug, Clone)]
pub struct JobRow {
    /// Random id (UUID v4).
    pub id: String,
    /// Owner.
    pub tenant: String,
    /// The input upload's id.
    pub upload: String,
    /// Current status.
    pub status: Status,
    /// What the job computes.
    pub spec: JobSpec,
    /// Submission time, ms since the Unix epoch.
    pub created_ms: i64,
    /// Start of the (latest) run.
    pub started_ms: Option<i64>,
    /// End of the run (or the dismissal).
    pub finished_ms: Option<i64>,
    /// The pipeline's report, when successful.
    pub report: Option<Report>,
    /// Why it failed.
    pub error: Option<String>,
    /// Result size in bytes, when successful.
    pub result_size: Option<u64>,
    /// Result SHA-256 (hex), when successful.
    pub result_sha256: Option<String>,
    /// The SLURM jobs submitted for it (executor `slurm`, once submitted).
    pub slurm: Option<SlurmRecord>,
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS uploads (
    id TEXT PRIMARY KEY,
    tenant TEXT NOT NULL,
    created_ms INTEGER NOT NULL,
    complete INTEGER NOT NULL,
    length INTEGER,
    size INTEGER NOT NULL,
    sha256 TEXT,
    format TEXT,
    filename TEXT,
    hint TEXT,
    points INTEGER,
    faces INTEGER
);
CREATE TABLE IF NOT EXISTS jobs (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    tenant TEXT NOT NULL,
    upload TEXT NOT NULL,
    status TEXT NOT NULL,
    spec TEXT NOT NULL,
    created_ms INTEGER NOT NULL,
    started_ms INTEGER,
    finished_ms INTEGER,
    report TEXT,
    error TEXT,
    result_size INTEGER,
    result_sha256 TEXT
);
CREATE INDEX IF NOT EXISTS jobs_by_tenant ON jobs (tenant, seq);
CREATE INDEX IF NOT EXISTS jobs_by_status ON jobs (status, seq);
CREATE INDEX IF NOT EXISTS jobs_by_upload ON jobs (upload);
CREATE INDEX IF NOT EXISTS uploads_by_tenant ON uploads (tenant, created_ms);
";

/// Columns added after the first schema: (column, type), added to an older database at open.
const ADDED_COLUMNS: [(&str, &str); 1] = [("slurm", "TEXT")];

const UPLOAD_COLUMNS: &str =
    "id, tenant, created_ms, complete, length, size, sha256, format, filename, hint, points, faces";
const JOB_COLUMNS: &str = "id, tenant, upload, status, spec, created_ms, started_ms, finished_ms, \
                           report, error, result_size, result_sha256, slurm";

/// SQLite integers are signed; sizes and counts never come near `i64::MAX`.
fn to_i64(v: u64) -> i64 {
    i64::try_from(v).unwrap_or(i64::MAX)
}

fn opt_u64(v: Option<i64>) -> Option<u64> {
    v.map(|x| u64::try_from(x).unwrap_or(0))
}

/// Column `i` of `r`, a format name (NULL: none).
fn stored_format(r: &Row<'_>, i: usize) -> rusqlite::Result<Option<Format>> {
    let Some(name) = r.get::<_, Option<String>>(i)? else {
        return Ok(None);
    };
    Format::from_name(&name).map(Some).ok_or_else(|| {
        rusqlite::Error::FromSqlConversionFailure(
            i,
            rusqlite::types::Type::Text,
            format!("unknown stored format `{name}`").into(),
        )
    })
}

fn upload_from(r: &Row<'_>) -> rusqlite::Result<Upload> {
    Ok(Upload {
        id: r.get(0)?,
        tenant: r.get(1)?,
        created_ms: r.get(2)?,
        complete: r.get(3)?,
        length: opt_u64(r.get(4)?),
        size: opt_u64(r.get(5)?).unwrap_or(0),
        sha256: r.get(6)?,
        format: stored_format(r, 7)?,
        filename: r.get(8)?,
        hint: r.get(9)?,
        points: opt_u64(r.get(10)?),
        faces: opt_u64(r.get(11)?),
    })
}

/// A row as stored, before its JSON columns are decoded.
struct RawJob {
    id: String,
    tenant: String,
    upload: String,
    status: String,
    spec: String,
    created_ms: i64,
    started_ms: Option<i64>,
    finished_ms: Option<i64>,
    report: Option<String>,
    error: Option<String>,
    result_size: Option<i64>,
    result_sha256: Option<String>,
    slurm: Option<String>,
}

fn raw_job(r: &Row<'_>) -> rusqlite::Result<RawJob> {
    Ok(RawJob {
        id: r.get(0)?,
        tenant: r.get(1)?,
        upload: r.get(2)?,
        status: r.get(3)?,
        spec: r.get(4)?,
        created_ms: r.get(5)?,
        started_ms: r.get(6)?,
        finished_ms: r.get(7)?,
        report: r.get(8)?,
        error: r.get(9)?,
        result_size: r.get(10)?,
        result_sha256: r.get(11)?,
        slurm: r.get(12)?,
    })
}

impl RawJob {
    fn decode(self) -> Result<JobRow, JobsError> {
        let corrupt = |what: &str, e: String| {
            JobsError::Internal(format!("job {}: stored {what} unreadable: {e}", self.id))
        };
        let status =
            Status::parse(&self.status).ok_or_else(|| corrupt("status", self.status.clone()))?;
        let spec = serde_json::from_str(&self.spec).map_err(|e| corrupt("spec", e.to_string()))?;
        let report = match &self.report {
            Some(text) => {
                Some(serde_json::from_str(text).map_err(|e| corrupt("report", e.to_string()))?)
            }
            None => None,
        };
        let slurm = match &self.slurm {
            Some(text) => {
                Some(serde_json::from_str(text).map_err(|e| corrupt("slurm", e.to_string()))?)
            }
            None => None,
        };
        Ok(JobRow {
            id: self.id,
            tenant: self.tenant,
            upload: self.upload,
            status,
            spec,
            created_ms: self.created_ms,
            started_ms: self.started_ms,
            finished_ms: self.finished_ms,
            report,
            error: self.error,
            result_size: opt_u64(self.result_size),
            result_sha256: self.result_sha256,
            slurm,
        })
    }
}

/// Adds the [`ADDED_COLUMNS`] a database of an earlier version lacks.
fn migrate(conn: &Connection) -> rusqlite::Result<()> {
    let have: Vec<String> = conn
        .prepare("SELECT name FROM pragma_table_info('jobs')")?
        .query_map([], |r| r.get(0))?
        .collect::<rusqlite::Result<_>>()?;
    for (col, ty) in ADDED_COLUMNS {
        if !have.iter().any(|h| h == col) {
            conn.execute_batch(&format!("ALTER TABLE jobs ADD COLUMN {col} {ty}"))?;
        }
    }
    Ok(())
}

/// The SQLite store. See the [module overview](self).
pub struct Store {
    // std Mutex: every critical section is one short statement, never held across an await.
    conn: Mutex<Connection>,
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store").finish_non_exhaustive()
    }
}

impl Store {
    /// Opens (creating if needed) the database at `path`.
    ///
    /// # Errors
    /// The file cannot be opened or is not a qemd database.
    pub fn open(path: &Path) -> Result<Store, JobsError> {
        let conn = Connection::open(path)?;
        conn.busy_timeout(std::time::Duration::from_secs(5))?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "NORMAL")?;
        conn.execute_batch(SCHEMA)?;
        migrate(&conn)?;
        Ok(Store {
            conn: Mutex::new(conn),
        })
    }

    /// An in-memory store (tests).
    ///
    /// # Errors
    /// SQLite failures.
    pub fn in_memory() -> Result<Store, JobsError> {
        let conn = Connection::open_in_memory()?;
        conn.execute_batch(SCHEMA)?;
        migrate(&conn)?;
        Ok(Store {
            conn: Mutex::new(conn),
        })
    }

    fn conn(&self) -> std::sync::MutexGuard<'_, Connection> {
        // A panic while holding the lock cannot leave SQLite inconsistent (each statement is
        // atomic), so a poisoned lock is still usable.
        self.conn.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// True when the database answers.
    pub fn ping(&self) -> bool {
        self.conn()
            .query_row("SELECT 1", [], |r| r.get::<_, i64>(0))
            .is_ok()
    }

    /// Inserts or replaces an upload row.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn put_upload(&self, u: &Upload) -> Result<(), JobsError> {
        self.conn().execute(
            &format!(
                "INSERT OR REPLACE INTO uploads ({UPLOAD_COLUMNS}) \
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12)"
            ),
            params![
                u.id,
                u.tenant,
                u.created_ms,
                u.complete,
                u.length.map(to_i64),
                to_i64(u.size),
                u.sha256,
                u.format.map(Format::name),
                u.filename,
                u.hint,
                u.points.map(to_i64),
                u.faces.map(to_i64),
            ],
        )?;
        Ok(())
    }

    /// A page of `tenant`'s uploads, newest first, and how many it has.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn list_uploads(
        &self,
        tenant: &str,
        limit: u64,
        offset: u64,
    ) -> Result<(Vec<Upload>, u64), JobsError> {
        let conn = self.conn();
        let mut st = conn.prepare(&format!(
            "SELECT {UPLOAD_COLUMNS} FROM uploads WHERE tenant = ?1 \
             ORDER BY created_ms DESC, id LIMIT ?2 OFFSET ?3"
        ))?;
        let rows = st
            .query_map(params![tenant, to_i64(limit), to_i64(offset)], upload_from)?
            .collect::<rusqlite::Result<Vec<Upload>>>()?;
        let total: i64 = conn.query_row(
            "SELECT COUNT(*) FROM uploads WHERE tenant = ?1",
            params![tenant],
            |r| r.get(0),
        )?;
        Ok((rows, opt_u64(Some(total)).unwrap_or(0)))
    }

    /// The upload `id`, if it exists (and belongs to `tenant` when given).
    ///
    /// # Errors
    /// SQLite failures.
    pub fn upload(&self, tenant: Option<&str>, id: &str) -> Result<Option<Upload>, JobsError> {
        Ok(self
            .conn()
            .query_row(
                &format!(
                    "SELECT {UPLOAD_COLUMNS} FROM uploads WHERE id = ?1 \
                     AND (?2 IS NULL OR tenant = ?2)"
                ),
                params![id, tenant],
                upload_from,
            )
            .optional()?)
    }

    /// Ids of uploads still receiving chunks.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn partial_uploads(&self) -> Result<Vec<String>, JobsError> {
        let conn = self.conn();
        let mut st = conn.prepare("SELECT id FROM uploads WHERE complete = 0")?;
        let ids = st
            .query_map([], |r| r.get(0))?
            .collect::<rusqlite::Result<Vec<String>>>()?;
        Ok(ids)
    }

    /// Deletes an upload row.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn delete_upload(&self, id: &str) -> Result<(), JobsError> {
        let _ = self
            .conn()
            .execute("DELETE FROM uploads WHERE id = ?1", params![id])?;
        Ok(())
    }

    /// Number of accepted or running jobs reading upload `id`.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn active_jobs_of_upload(&self, id: &str) -> Result<u64, JobsError> {
        let n: i64 = self.conn().query_row(
            "SELECT COUNT(*) FROM jobs WHERE upload = ?1 AND status IN ('accepted', 'running')",
            params![id],
            |r| r.get(0),
        )?;
        Ok(opt_u64(Some(n)).unwrap_or(0))
    }

    /// Inserts a new job.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn insert_job(&self, j: &JobRow) -> Result<(), JobsError> {
        let spec = serde_json::to_string(&j.spec)
            .map_err(|e| JobsError::Internal(format!("cannot encode a job spec: {e}")))?;
        self.conn().execute(
            "INSERT INTO jobs (id, tenant, upload, status, spec, created_ms) \
             VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            params![
                j.id,
                j.tenant,
                j.upload,
                j.status.as_str(),
                spec,
                j.created_ms
            ],
        )?;
        Ok(())
    }

    /// The job `id`, if it exists (and belongs to `tenant` when given).
    ///
    /// # Errors
    /// SQLite failures, an unreadable row.
    pub fn job(&self, tenant: Option<&str>, id: &str) -> Result<Option<JobRow>, JobsError> {
        let raw = self
            .conn()
            .query_row(
                &format!(
                    "SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?1 AND (?2 IS NULL OR tenant = ?2)"
                ),
                params![id, tenant],
                raw_job,
            )
            .optional()?;
        raw.map(RawJob::decode).transpose()
    }

    /// A page of `tenant`'s jobs, newest first, optionally of one status; and the number of jobs
    /// matching.
    ///
    /// # Errors
    /// SQLite failures, an unreadable row.
    pub fn list_jobs(
        &self,
        tenant: &str,
        status: Option<Status>,
        limit: u64,
        offset: u64,
    ) -> Result<(Vec<JobRow>, u64), JobsError> {
        let conn = self.conn();
        let status = status.map(Status::as_str);
        let mut st = conn.prepare(&format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE tenant = ?1 AND (?2 IS NULL OR status = ?2) \
             ORDER BY seq DESC LIMIT ?3 OFFSET ?4"
        ))?;
        let raws = st
            .query_map(
                params![tenant, status, to_i64(limit), to_i64(offset)],
                raw_job,
            )?
            .collect::<rusqlite::Result<Vec<RawJob>>>()?;
        let total: i64 = conn.query_row(
            "SELECT COUNT(*) FROM jobs WHERE tenant = ?1 AND (?2 IS NULL OR status = ?2)",
            params![tenant, status],
            |r| r.get(0),
        )?;
        let rows = raws
            .into_iter()
            .map(RawJob::decode)
            .collect::<Result<Vec<_>, _>>()?;
        Ok((rows, opt_u64(Some(total)).unwrap_or(0)))
    }

    /// Ids of the jobs in `status`, oldest first (start-up recovery).
    ///
    /// # Errors
    /// SQLite failures.
    pub fn ids_with_status(&self, status: Status) -> Result<Vec<String>, JobsError> {
        let conn = self.conn();
        let mut st = conn.prepare("SELECT id FROM jobs WHERE status = ?1 ORDER BY seq")?;
        let ids = st
            .query_map(params![status.as_str()], |r| r.get(0))?
            .collect::<rusqlite::Result<Vec<String>>>()?;
        Ok(ids)
    }

    /// Ids of the accepted jobs that have SLURM jobs recorded, oldest first (start-up: they
    /// re-attach at once instead of waiting for a worker).
    ///
    /// # Errors
    /// SQLite failures.
    pub fn accepted_on_slurm(&self) -> Result<Vec<String>, JobsError> {
        let conn = self.conn();
        let mut st = conn.prepare(
            "SELECT id FROM jobs WHERE status = 'accepted' AND slurm IS NOT NULL ORDER BY seq",
        )?;
        let ids = st
            .query_map([], |r| r.get(0))?
            .collect::<rusqlite::Result<Vec<String>>>()?;
        Ok(ids)
    }

    /// Stores the SLURM jobs of job `id` (synchronously committed before they are relied on).
    ///
    /// # Errors
    /// SQLite failures.
    pub fn set_slurm(&self, id: &str, record: &SlurmRecord) -> Result<(), JobsError> {
        let text = serde_json::to_string(record)
            .map_err(|e| JobsError::Internal(format!("cannot encode a SLURM record: {e}")))?;
        let _ = self.conn().execute(
            "UPDATE jobs SET slurm = ?2 WHERE id = ?1",
            params![id, text],
        )?;
        Ok(())
    }

    /// Job counts by status (every status, zeros included).
    ///
    /// # Errors
    /// SQLite failures.
    pub fn count_by_status(&self) -> Result<Vec<(Status, u64)>, JobsError> {
        let conn = self.conn();
        let mut st = conn.prepare("SELECT status, COUNT(*) FROM jobs GROUP BY status")?;
        let found = st
            .query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))?
            .collect::<rusqlite::Result<Vec<_>>>()?;
        Ok(Status::ALL
            .into_iter()
            .map(|s| {
                let n = found
                    .iter()
                    .find(|(name, _)| name == s.as_str())
                    .map_or(0, |(_, n)| opt_u64(Some(*n)).unwrap_or(0));
                (s, n)
            })
            .collect())
    }

    /// Moves job `id` from `from` to `to` (with the given timestamps); false when it was not in
    /// `from` (someone else changed it first).
    ///
    /// # Errors
    /// SQLite failures.
    pub fn transition(
        &self,
        id: &str,
        from: Status,
        to: Status,
        started_ms: Option<i64>,
        finished_ms: Option<i64>,
    ) -> Result<bool, JobsError> {
        let n = self.conn().execute(
            "UPDATE jobs SET status = ?3, started_ms = COALESCE(?4, started_ms), \
             finished_ms = ?5 WHERE id = ?1 AND status = ?2",
            params![id, from.as_str(), to.as_str(), started_ms, finished_ms],
        )?;
        Ok(n == 1)
    }

    /// Every running job back to accepted (start-up: their server died); returns how many.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn requeue_running(&self) -> Result<usize, JobsError> {
        Ok(self.conn().execute(
            "UPDATE jobs SET status = 'accepted' WHERE status = 'running'",
            [],
        )?)
    }

    /// Records a successful run; false when the job was no longer running (dismissed meanwhile).
    ///
    /// # Errors
    /// SQLite failures.
    pub fn finish_success(
        &self,
        id: &str,
        finished_ms: i64,
        report: &Report,
        size: u64,
        sha256: &str,
    ) -> Result<bool, JobsError> {
        let report = serde_json::to_string(report)
            .map_err(|e| JobsError::Internal(format!("cannot encode a report: {e}")))?;
        let n = self.conn().execute(
            "UPDATE jobs SET status = 'successful', finished_ms = ?2, report = ?3, \
             result_size = ?4, result_sha256 = ?5, error = NULL \
             WHERE id = ?1 AND status = 'running'",
            params![id, finished_ms, report, to_i64(size), sha256],
        )?;
        Ok(n == 1)
    }

    /// Records a failed run; false when the job was no longer running.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn finish_failure(
        &self,
        id: &str,
        finished_ms: i64,
        error: &str,
    ) -> Result<bool, JobsError> {
        let n = self.conn().execute(
            "UPDATE jobs SET status = 'failed', finished_ms = ?2, error = ?3 \
             WHERE id = ?1 AND status = 'running'",
            params![id, finished_ms, error],
        )?;
        Ok(n == 1)
    }

    /// Marks job `id` dismissed (whatever its status); false when it already was.
    ///
    /// # Errors
    /// SQLite failures.
    pub fn dismiss(&self, id: &str, finished_ms: i64) -> Result<bool, JobsError> {
        let n = self.conn().execute(
            "UPDATE jobs SET status = 'dismissed', finished_ms = ?2, \
             result_size = NULL, result_sha256 = NULL \
             WHERE id = ?1 AND status != 'dismissed'",
            params![id, finished_ms],
        )?;
        Ok(n == 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue51_results_download_under_the_inputs_name() {
        let mut spec = job("j1", "t").spec;
        let name = |spec: &JobSpec| spec.result_filename("j1");
        assert_eq!(name(&spec), "j1.ply");
        for (input, format, want) in [
            ("scan.laz", Format::Laz, "scan.denoised.laz"),
            ("scan.laz", Format::Las, "scan.denoised.las"),
            ("site.copc.laz", Format::Copc, "site.denoised.copc.laz"),
            ("sweep.pcd.bin", Format::Nuscenes, "sweep.denoised.pcd.bin"),
            ("C:\\data\\bunny.ply", Format::Ply, "bunny.denoised.ply"),
            ("dir/no-extension", Format::Xyz, "no-extension.denoised.xyz"),
            (".ply", Format::Ply, "j1.ply"),
        ] {
            spec.input_filename = Some(input.into());
            spec.output_format = format;
            assert_eq!(name(&spec), want, "{input}");
        }
    }

    fn job(id: &str, tenant: &str) -> JobRow {
        JobRow {
            id: id.into(),
            tenant: tenant.into(),
            upload: "u1".into(),
            status: Status::Accepted,
            spec: JobSpec {
                denoise: DenoiseSpec::default(),
                output_format: Format::Ply,
                memory_budget: 1 << 30,
                tile_points: Some(5000),
                executor: Executor::Local,
                input_filename: None,
            },
            created_ms: 1,
            started_ms: None,
            finished_ms: None,
            report: None,
            error: None,
            result_size: None,
            result_sha256: None,
            slurm: None,
        }
    }

    #[test]
    fn rows_round_trip_and_tenants_are_filters() {
        let s = Store::in_memory().unwrap();
        let u = Upload {
            id: "u1".into(),
            tenant: "a".into(),
            created_ms: 5,
            complete: true,
            length: None,
            size: 10,
            sha256: Some("ab".into()),
            format: Some(Format::Ply),
            filename: None,
            hint: None,
            points: Some(3),
            faces: None,
        };
        s.put_upload(&u).unwrap();
        assert_eq!(s.upload(Some("a"), "u1").unwrap(), Some(u.clone()));
        assert_eq!(s.upload(Some("b"), "u1").unwrap(), None);
        assert_eq!(s.upload(None, "u1").unwrap(), Some(u));
        s.insert_job(&job("j1", "a")).unwrap();
        s.insert_job(&job("j2", "a")).unwrap();
        s.insert_job(&job("j3", "b")).unwrap();
        assert!(s.job(Some("b"), "j1").unwrap().is_none());
        let j = s.job(Some("a"), "j1").unwrap().unwrap();
        assert_eq!(j.spec.tile_points, Some(5000));
        let (page, total) = s.list_jobs("a", None, 1, 0).unwrap();
        assert_eq!((page.len(), total), (1, 2));
        assert_eq!(page[0].id, "j2");
        assert_eq!(s.active_jobs_of_upload("u1").unwrap(), 3);

        assert!(
            s.transition("j1", Status::Accepted, Status::Running, Some(2), None)
                .unwrap()
        );
        assert!(
            !s.transition("j1", Status::Accepted, Status::Running, Some(2), None)
                .unwrap()
        );
        assert!(s.dismiss("j1", 3).unwrap());
        assert!(!s.finish_failure("j1", 4, "x").unwrap());
        assert_eq!(
            s.job(None, "j1").unwrap().unwrap().status,
            Status::Dismissed
        );
        assert!(
            s.transition("j2", Status::Accepted, Status::Running, Some(2), None)
                .unwrap()
        );
        assert_eq!(s.requeue_running().unwrap(), 1);
        assert_eq!(
            s.ids_with_status(Status::Accepted).unwrap(),
            vec!["j2", "j3"]
        );
        let counts = s.count_by_status().unwrap();
        assert!(counts.contains(&(Status::Accepted, 2)));
        assert!(counts.contains(&(Status::Dismissed, 1)));
        assert!(counts.contains(&(Status::Failed, 0)));
        let (page, total) = s.list_jobs("a", Some(Status::Dismissed), 10, 0).unwrap();
        assert_eq!((page.len(), total), (1, 1));
    }

    #[test]
    fn slurm_records_persist_and_old_databases_gain_the_column() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("q.sqlite");
        {
            // A database of the first schema (no `slurm` column) with a job in it.
            let conn = Connection::open(&path).unwrap();
            conn.execute_batch(SCHEMA).unwrap();
            let mut spec = serde_json::to_value(job("old", "t").spec).unwrap();
            assert!(spec.as_object_mut().unwrap().remove("executor").is_some());
            conn.execute(
                "INSERT INTO jobs (id, tenant, upload, status, spec, created_ms) \
                 VALUES ('old', 't', 'u', 'accepted', ?1, 1)",
                params![spec.to_string()],
            )
            .unwrap();
        }
        let s = Store::open(&path).unwrap();
        let old = s.job(None, "old").unwrap().unwrap();
        assert_eq!(old.spec.executor, Executor::Local);
        assert_eq!(old.slurm, None);
        let mut j = job("j1", "a");
        j.spec.executor = Executor::Slurm;
        s.insert_job(&j).unwrap();
        assert!(s.accepted_on_slurm().unwrap().is_empty());
        let rec = SlurmRecord {
            jobs: vec![crate::jobs::slurm::ArrayJob {
                phase: crate::pipeline::scaleout::Phase::Partition,
                id: "42".into(),
                tasks: 1,
            }],
            ..SlurmRecord::default()
        };
        s.set_slurm("j1", &rec).unwrap();
        drop(s);
        let s = Store::open(&path).unwrap();
        let j = s.job(None, "j1").unwrap().unwrap();
        assert_eq!(j.spec.executor, Executor::Slurm);
        assert_eq!(j.slurm, Some(rec));
        assert_eq!(s.accepted_on_slurm().unwrap(), vec!["j1"]);
    }
}
