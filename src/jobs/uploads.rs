//! Uploads: bodies streamed to disk (never held whole in memory), hashed on the way, then sniffed
//! and validated by opening them with the format's reader.
//!
//! Two ways in:
//!
//! * **One request** ([`Jobs::receive`]): the body streams into `uploads/<id>.part`; the row is
//!   written only once the file is complete and valid, so a broken request leaves nothing.
//! * **Resumable**, tus-style ([`Jobs::create_resumable`], [`Jobs::append`]): the row exists from
//!   the start with its declared length; each PATCH appends at the offset the server has (the
//!   `.part` file's length, which survives restarts) and an interrupted PATCH keeps the bytes it
//!   delivered. When the last byte arrives the file is hashed, sniffed and validated like a
//!   one-request upload; if that fails (format unknown or content invalid) the upload is kept,
//!   all its bytes, and the error says how to name its format (issue 15: a finished upload is
//!   never thrown away).

use std::path::{Path, PathBuf};

use futures_util::{Stream, StreamExt};
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;
use tracing::info;

use super::ids::{hex, new_id, now_ms, sha256_file, valid_id};
use super::requests::{canonical_format, format_of};
use super::store::Upload;
use super::{Jobs, JobsError, bridge};
use crate::io::Format;
use crate::io::sniff::{SNIFF_LEN, sniff};

/// Removes a file when dropped unless disarmed (a request abandoned mid-body leaves nothing).
struct RemoveOnDrop(Option<PathBuf>);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        if let Some(p) = self.0.take() {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// How much of an oversized body is read and discarded before the 413 goes out: a client still
/// sending when the server answers and closes would see a reset instead of the answer.
pub const DRAIN_MAX: u64 = 8 << 20;

/// Reads and discards up to `max` more bytes of `body` (see [`DRAIN_MAX`]).
pub async fn discard<S, B, E>(body: &mut S, max: u64)
where
    S: Stream<Item = Result<B, E>> + Unpin + Send,
    B: AsRef<[u8]>,
{
    let mut seen = 0u64;
    while seen <= max {
        match body.next().await {
            Some(Ok(chunk)) => seen += chunk.as_ref().len() as u64,
            _ => break,
        }
    }
}

/// The format a client declared, checked.
fn declared(hint: &super::FormatHint) -> Result<Option<String>, JobsError> {
    if let Some(f) = &hint.format {
        return canonical_format(f).map(Some).ok_or_else(|| {
            JobsError::UnsupportedFormat(format!(
                "unknown format `{f}` (expected ply, obj, off, xyz, txt, pts, bin, pcd, las or laz)"
            ))
        });
    }
    Ok(hint
        .filename
        .as_deref()
        .and_then(|n| Path::new(n).extension())
        .and_then(|e| e.to_str())
        .and_then(canonical_format))
}

/// Checks a client's format hint before any byte is received.
///
/// # Errors
/// [`JobsError::UnsupportedFormat`] for an unknown `format`.
pub fn check_hint(hint: &super::FormatHint) -> Result<(), JobsError> {
    declared(hint).map(|_| ())
}

/// What validation learnt about a complete upload.
struct Inspected {
    format: Format,
    points: Option<u64>,
    faces: Option<u64>,
}

/// What happens to the bytes of an upload that fails validation.
#[derive(Clone, Copy, PartialEq, Eq)]
enum OnFailure {
    /// Removed (a one-request upload: the client still holds the body it just sent).
    Remove,
    /// Kept as the `.part` file (a finished resumable upload: the client may have sent it over
    /// hours and may no longer hold it; it can name the format and try again).
    Keep,
}

/// Picks the format of the complete file `part` (declared, else sniffed), moves it to its final
/// name `<id>.<ext>` and opens it with the format's reader. On failure the file is removed or
/// moved back to `part`, as `on_failure` says.
fn inspect(
    part: &Path,
    final_of: impl Fn(Format) -> PathBuf,
    declared: Option<String>,
    on_failure: OnFailure,
) -> Result<(Inspected, PathBuf), JobsError> {
    use std::io::Read;
    let mut head = Vec::with_capacity(SNIFF_LEN);
    let f = std::fs::File::open(part).map_err(|e| JobsError::io("open an upload", e))?;
    f.take(SNIFF_LEN as u64)
        .read_to_end(&mut head)
        .map_err(|e| JobsError::io("read an upload", e))?;
    let sniffed = sniff(&head).map(crate::io::Format::name);
    let ext = match (declared, sniffed) {
        // LAS, LAZ and COPC share a name and a media type; the header says which it is.
        (Some(d), Some(s)) if format_of(&d)?.is_las() && format_of(s)?.is_las() => s.to_string(),
        (Some(d), _) => d,
        (None, Some(s)) => s.to_string(),
        (None, None) => {
            if on_failure == OnFailure::Remove {
                let _ = std::fs::remove_file(part);
            }
            return Err(JobsError::UnsupportedFormat(
                "cannot tell the format from the content; name it with ?format= (ply, las, laz, \
                 pcd, obj, off, xyz, pts or bin)"
                    .into(),
            ));
        }
    };
    let format = format_of(&ext)?;
    let path = final_of(format);
    std::fs::rename(part, &path).map_err(|e| JobsError::io("store an upload", e))?;
    let fail = |msg: String| {
        match on_failure {
            OnFailure::Remove => {
                let _ = std::fs::remove_file(&path);
            }
            OnFailure::Keep => {
                let _ = std::fs::rename(&path, part);
            }
        }
        let shown = msg.replace(&path.display().to_string(), "upload");
        JobsError::Rejected(format!("not a valid {ext} file: {shown}"))
    };
    let mut src = match crate::io::open(&path, Some(format)) {
        Ok(s) => s,
        Err(e) => return Err(fail(e.to_string())),
    };
    let info = src.info().clone();
    let mut batch = crate::points::PointBatch::with_capacity(info.schema.record_len, 1024);
    let read = match src.read_batch(&mut batch, 1024) {
        Ok(n) => n,
        Err(e) => return Err(fail(e.to_string())),
    };
    if read == 0 || info.len == Some(0) {
        return Err(fail("it holds no points".into()));
    }
    Ok((
        Inspected {
            format,
            points: info.len,
            faces: info.faces,
        },
        path,
    ))
}

impl Jobs {
    fn check_size(&self, size: u64) -> Result<(), JobsError> {
        let limit = self.inner.settings.max_upload_size;
        if size > limit {
            return Err(JobsError::OverLimit { limit });
        }
        Ok(())
    }

    /// Receives a whole upload for `tenant` from `body`, streaming it to disk and hashing it on
    /// the way; `length` is the size the client announced (checked against the limit first).
    ///
    /// # Errors
    /// [`JobsError::OverLimit`], [`JobsError::BodyRead`] when the body breaks off,
    /// [`JobsError::UnsupportedFormat`], [`JobsError::Rejected`].
    pub async fn receive<S, B, E>(
        &self,
        tenant: &str,
        length: Option<u64>,
        hint: super::FormatHint,
        mut body: S,
    ) -> Result<Upload, JobsError>
    where
        S: Stream<Item = Result<B, E>> + Unpin + Send,
        B: AsRef<[u8]>,
        E: std::fmt::Display,
    {
        if let Some(n) = length
            && let Err(e) = self.check_size(n)
        {
            if n - self.inner.settings.max_upload_size <= DRAIN_MAX {
                discard(&mut body, n).await;
            }
            return Err(e);
        }
        let declared = declared(&hint)?;
        let id = new_id();
        let part = self.part_path(&id);
        let mut guard = RemoveOnDrop(Some(part.clone()));
        let file = tokio::fs::File::create(&part)
            .await
            .map_err(|e| JobsError::io("create an upload", e))?;
        let mut out = tokio::io::BufWriter::with_capacity(1 << 20, file);
        let mut hasher = Sha256::new();
        let mut size = 0u64;
        while let Some(chunk) = body.next().await {
            let chunk = chunk.map_err(|e| JobsError::BodyRead(format!("reading the body: {e}")))?;
            let bytes = chunk.as_ref();
            size += bytes.len() as u64;
            if let Err(e) = self.check_size(size) {
                discard(&mut body, DRAIN_MAX).await;
                return Err(e);
            }
            hasher.update(bytes);
            out.write_all(bytes)
                .await
                .map_err(|e| JobsError::io("write an upload", e))?;
        }
        out.flush()
            .await
            .map_err(|e| JobsError::io("write an upload", e))?;
        let file = out.into_inner();
        file.sync_all()
            .await
            .map_err(|e| JobsError::io("sync an upload", e))?;
        drop(file);
        let sha = hex(&hasher.finalize());
        let me = self.clone();
        let uid = id.clone();
        let (inspected, path) = bridge::blocking(move || {
            inspect(
                &part,
                |ext| me.upload_path(&uid, ext),
                declared,
                OnFailure::Remove,
            )
        })
        .await??;
        guard.0 = Some(path);
        let upload = Upload {
            id,
            tenant: tenant.to_string(),
            created_ms: now_ms(),
            complete: true,
            length: Some(size),
            size,
            sha256: Some(sha),
            format: Some(inspected.format),
            filename: hint.filename,
            hint: hint.format,
            points: inspected.points,
            faces: inspected.faces,
        };
        let row = upload.clone();
        self.db(move |s| s.put_upload(&row)).await?;
        guard.0 = None;
        self.booked(&upload);
        Ok(upload)
    }

    fn booked(&self, u: &Upload) {
        let m = self.metrics();
        m.uploads.inc();
        m.upload_bytes.inc_by(u.size);
        info!(upload = %u.id, tenant = %u.tenant, size = u.size, format = ?u.format, points = ?u.points, "upload complete");
    }

    /// Creates a resumable upload of `length` bytes for `tenant` (tus creation): an empty file
    /// and a row, completed by [`Jobs::append`].
    ///
    /// # Errors
    /// [`JobsError::OverLimit`], [`JobsError::UnsupportedFormat`] for an unknown format hint.
    pub async fn create_resumable(
        &self,
        tenant: &str,
        length: u64,
        hint: super::FormatHint,
    ) -> Result<Upload, JobsError> {
        self.check_size(length)?;
        if length == 0 {
            return Err(JobsError::Rejected("an upload cannot be empty".into()));
        }
        let _ = declared(&hint)?;
        let upload = Upload {
            id: new_id(),
            tenant: tenant.to_string(),
            created_ms: now_ms(),
            complete: false,
            length: Some(length),
            size: 0,
            sha256: None,
            format: None,
            filename: hint.filename,
            hint: hint.format,
            points: None,
            faces: None,
        };
        let part = self.part_path(&upload.id);
        tokio::fs::File::create(&part)
            .await
            .map_err(|e| JobsError::io("create an upload", e))?;
        let row = upload.clone();
        self.db(move |s| s.put_upload(&row)).await?;
        info!(upload = %upload.id, tenant, length, "resumable upload created");
        Ok(upload)
    }

    /// The upload `id` of `tenant`; for a resumable one in progress, `size` is the offset the
    /// server has.
    ///
    /// # Errors
    /// [`JobsError::NoSuch`].
    pub async fn upload(&self, tenant: &str, id: &str) -> Result<Upload, JobsError> {
        if !valid_id(id) {
            return Err(JobsError::NoSuch("upload"));
        }
        let (t, i) = (tenant.to_string(), id.to_string());
        let mut u = self
            .db(move |s| s.upload(Some(&t), &i))
            .await?
            .ok_or(JobsError::NoSuch("upload"))?;
        if !u.complete {
            u.size = tokio::fs::metadata(self.part_path(id))
                .await
                .map_or(0, |m| m.len());
        }
        Ok(u)
    }

    /// Appends `body` to resumable upload `id` of `tenant` at `offset` (tus PATCH). The bytes
    /// received before a broken connection are kept. When the upload is complete it is hashed,
    /// sniffed and validated.
    ///
    /// `hint`, when given, replaces the format hint of the creation request. A finished upload
    /// that fails validation (its format cannot be told, or it is not a valid file of its
    /// format) is **kept**, all its bytes, still incomplete: a PATCH with an empty body at its
    /// full length and a new `hint` validates it again; DELETE removes it.
    ///
    /// # Errors
    /// [`JobsError::NoSuch`], [`JobsError::WrongState`] (offset mismatch, already complete, a
    /// concurrent PATCH), [`JobsError::OverLimit`] beyond the declared length (the PATCH then
    /// keeps none of its bytes),
    /// [`JobsError::BodyRead`] when the body breaks off, and on completion the errors of
    /// validation (saying that the upload is kept and how to name its format).
    pub async fn append<S, B, E>(
        &self,
        tenant: &str,
        id: &str,
        offset: u64,
        hint: Option<super::FormatHint>,
        mut body: S,
    ) -> Result<Upload, JobsError>
    where
        S: Stream<Item = Result<B, E>> + Unpin + Send,
        B: AsRef<[u8]>,
        E: std::fmt::Display,
    {
        if let Some(h) = &hint {
            check_hint(h)?;
        }
        let mut upload = self.upload(tenant, id).await?;
        if upload.complete {
            return Err(JobsError::WrongState {
                detail: format!("upload {id} is already complete"),
                offset: Some(upload.size),
            });
        }
        let length = upload.length.unwrap_or(0);
        // One PATCH per upload at a time: a second one would interleave bytes.
        let _lock = self.lock_patch(id, "another PATCH of upload {id} is in progress")?;
        let part = self.part_path(id);
        // Gone since the row was read: a DELETE finished in between (issue 15: this was a 500).
        let gone = |e: std::io::Error, what: &str| match e.kind() {
            std::io::ErrorKind::NotFound => JobsError::NoSuch("upload"),
            _ => JobsError::io(what, e),
        };
        let have = tokio::fs::metadata(&part)
            .await
            .map_err(|e| gone(e, "stat an upload"))?
            .len();
        if offset != have {
            return Err(JobsError::WrongState {
                detail: format!("Upload-Offset is {offset}, the server has {have} bytes"),
                offset: Some(have),
            });
        }
        let file = tokio::fs::OpenOptions::new()
            .append(true)
            .open(&part)
            .await
            .map_err(|e| gone(e, "open an upload"))?;
        let mut out = tokio::io::BufWriter::with_capacity(1 << 20, file);
        let mut size = have;
        let mut broken = None;
        while let Some(chunk) = body.next().await {
            let bytes = match &chunk {
                Ok(b) => b.as_ref(),
                Err(e) => {
                    broken = Some(JobsError::BodyRead(format!("reading the body: {e}")));
                    break;
                }
            };
            if size + bytes.len() as u64 > length {
                broken = Some(JobsError::OverLimit { limit: length });
                discard(&mut body, DRAIN_MAX).await;
                break;
            }
            out.write_all(bytes)
                .await
                .map_err(|e| JobsError::io("write an upload", e))?;
            size += bytes.len() as u64;
        }
        // Whatever arrived stays: the client resumes from the offset HEAD reports. A PATCH past
        // Upload-Length keeps none of its bytes (issue 51: it kept its first 16 KB): the
        // upload is as it was before it.
        out.flush()
            .await
            .map_err(|e| JobsError::io("write an upload", e))?;
        let file = out.into_inner();
        if matches!(broken, Some(JobsError::OverLimit { .. })) {
            file.set_len(have)
                .await
                .map_err(|e| JobsError::io("truncate an upload", e))?;
        }
        file.sync_data()
            .await
            .map_err(|e| JobsError::io("sync an upload", e))?;
        drop(file);
        if let Some(e) = broken {
            return Err(e);
        }
        upload.size = size;
        if let Some(h) = hint {
            // Recorded before validation, so a restart or a retry sees the client's choice.
            (upload.hint, upload.filename) =
                (h.format.or(upload.hint), h.filename.or(upload.filename));
            let mut row = upload.clone();
            row.size = 0;
            self.db(move |s| s.put_upload(&row)).await?;
        }
        if size < length {
            return Ok(upload);
        }
        // Complete: hash, sniff, validate, record.
        let me = self.clone();
        let uid = id.to_string();
        let hint = super::FormatHint {
            format: upload.hint.clone(),
            filename: upload.filename.clone(),
        };
        let done = bridge::blocking(move || {
            let sha = sha256_file(&part)?;
            let declared = declared(&hint)?;
            let (inspected, _) = inspect(
                &part,
                |ext| me.upload_path(&uid, ext),
                declared,
                OnFailure::Keep,
            )?;
            Ok::<_, JobsError>((sha, inspected))
        })
        .await?;
        match done {
            Ok((sha, inspected)) => {
                upload.complete = true;
                upload.sha256 = Some(sha);
                upload.format = Some(inspected.format);
                upload.points = inspected.points;
                upload.faces = inspected.faces;
                let row = upload.clone();
                self.db(move |s| s.put_upload(&row)).await?;
                self.booked(&upload);
                Ok(upload)
            }
            Err(e) => {
                // Every byte stays in the `.part` file, the row stays incomplete: the client
                // names the format (or deletes the upload); nothing it sent is lost.
                let kept = |m: String| {
                    format!(
                        "{m}; upload {id} is kept with all {length} bytes: name its format with \
                         PATCH /v1/uploads/{id}?format=… (Upload-Offset: {length}, empty body) \
                         or DELETE it"
                    )
                };
                info!(upload = id, tenant, error = %e, "finished upload kept, not valid as it is");
                Err(match e {
                    JobsError::UnsupportedFormat(m) => JobsError::UnsupportedFormat(kept(m)),
                    JobsError::Rejected(m) => JobsError::Rejected(kept(m)),
                    e => e,
                })
            }
        }
    }

    /// Deletes upload `id` of `tenant` (tus termination) and its file.
    ///
    /// # Errors
    /// [`JobsError::NoSuch`], [`JobsError::WrongState`] while a queued or running job reads it
    /// or a PATCH writes to it.
    pub async fn delete_upload(&self, tenant: &str, id: &str) -> Result<(), JobsError> {
        let u = self.upload(tenant, id).await?;
        // Not while a PATCH writes to it (its bytes would go to a removed file).
        let _lock = self.lock_patch(id, "a PATCH of upload {id} is in progress; retry")?;
        let i = id.to_string();
        let active = self.db(move |s| s.active_jobs_of_upload(&i)).await?;
        if active > 0 {
            return Err(JobsError::WrongState {
                detail: format!("{active} queued or running job(s) read upload {id}"),
                offset: None,
            });
        }
        let path = match &u.format {
            Some(f) if u.complete => self.upload_path(id, *f),
            _ => self.part_path(id),
        };
        let _ = tokio::fs::remove_file(path).await;
        let i = id.to_string();
        self.db(move |s| s.delete_upload(&i)).await?;
        info!(upload = id, tenant, "upload deleted");
        Ok(())
    }
}

impl Jobs {
    /// Takes upload `id`'s PATCH lock, or answers 409 with `busy` (`{id}` replaced).
    fn lock_patch(&self, id: &str, busy: &str) -> Result<PatchLock, JobsError> {
        let mut p = self
            .inner
            .patching
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if !p.insert(id.to_string()) {
            return Err(JobsError::WrongState {
                detail: busy.replace("{id}", id),
                offset: None,
            });
        }
        Ok(PatchLock(self.clone(), id.to_string()))
    }
}

/// Releases an upload's PATCH lock when the request ends (or is abandoned).
struct PatchLock(Jobs, String);

impl Drop for PatchLock {
    fn drop(&mut self) {
        let _ = self
            .0
            .inner
            .patching
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&self.1);
    }
}
