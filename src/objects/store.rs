//! One S3 prefix as a flat set of named objects, through the `object_store` crate, driven by a
//! current-thread tokio runtime this value owns (the pipeline below it stays synchronous).
//!
//! Endpoint, region and credentials come from the standard `AWS_*` environment
//! (`AWS_ENDPOINT_URL`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`,
//! `AWS_ALLOW_HTTP` for a plain-HTTP server on 127.0.0.1), as every S3 tool reads them.
//!
//! Transfers stream: a download is written to a temporary file beside its target and renamed
//! onto it; an upload of more than [`SMALL`] bytes goes as a multipart upload read from the file
//! in [`CHUNK`]-byte parts, so memory stays bounded whatever the object's size.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::Path as FsPath;
use std::sync::Arc;
use std::time::Duration;

use futures_util::StreamExt;
use object_store::aws::AmazonS3Builder;
use object_store::path::Path;
use object_store::{ObjectStore, PutMode, PutOptions, PutPayload, RetryConfig, WriteMultipart};

use super::ObjectsError;

/// Objects up to this size are uploaded in one request (conditional when asked).
pub const SMALL: u64 = 16 << 20;
/// The part size of a multipart upload.
pub const CHUNK: usize = 8 << 20;
/// Transfers in flight at once.
pub const PARALLEL: usize = 8;

/// How an upload treats an object that is already there.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Put {
    /// Never replace it (a commit): a single conditional request (`If-None-Match: *`) for a
    /// small object; a large one is skipped when one of the same size is there (the bytes of a
    /// job's files are deterministic, so a duplicate task wrote the same ones).
    Create,
    /// Replace it (only the plan file, which the partition rewrites).
    Overwrite,
}

/// One S3 prefix (see the module overview).
pub struct Store {
    rt: tokio::runtime::Runtime,
    s3: Arc<dyn ObjectStore>,
    prefix: String,
    url: String,
}

impl Store {
    /// Connects to `bucket` (nothing is sent until the first request).
    ///
    /// # Errors
    /// [`ObjectsError::Store`] for a configuration the client refuses or a runtime that cannot
    /// start.
    pub fn open(bucket: &str, prefix: &str, url: &str) -> Result<Store, ObjectsError> {
        let bad = |detail: String| ObjectsError::store(url, &detail);
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| bad(format!("cannot start the I/O runtime: {e}")))?;
        // Fail in about a minute, not after object_store's default three, when the server is down.
        let retry = RetryConfig {
            max_retries: 4,
            retry_timeout: Duration::from_secs(60),
            ..RetryConfig::default()
        };
        let s3 = AmazonS3Builder::from_env()
            .with_bucket_name(bucket)
            .with_retry(retry)
            .build()
            .map_err(|e| bad(e.to_string()))?;
        Ok(Store {
            rt,
            s3: Arc::new(s3),
            prefix: prefix.to_string(),
            url: url.to_string(),
        })
    }

    /// The URL this store was opened for.
    pub fn url(&self) -> &str {
        &self.url
    }

    fn key(&self, name: &str) -> Path {
        if self.prefix.is_empty() {
            Path::from(name)
        } else {
            Path::from(format!("{}/{name}", self.prefix))
        }
    }

    fn err(&self, name: &str, e: impl std::fmt::Display) -> ObjectsError {
        ObjectsError::store(&format!("{}/{name}", self.url), &e.to_string())
    }

    /// Every object under the prefix: name (relative to it) → size.
    ///
    /// # Errors
    /// The listing fails (server down, no such bucket, refused credentials).
    pub fn list(&self) -> Result<BTreeMap<String, u64>, ObjectsError> {
        let root = (!self.prefix.is_empty()).then(|| Path::from(self.prefix.as_str()));
        let strip = if self.prefix.is_empty() {
            String::new()
        } else {
            format!("{}/", self.prefix)
        };
        self.rt.block_on(async {
            let mut out = BTreeMap::new();
            let mut s = self.s3.list(root.as_ref());
            while let Some(m) = s.next().await {
                let m = m.map_err(|e| ObjectsError::store(&self.url, &e.to_string()))?;
                let key = m.location.to_string();
                if let Some(name) = key.strip_prefix(&strip) {
                    out.insert(name.to_string(), m.size);
                }
            }
            Ok(out)
        })
    }

    /// Downloads each `(name, target)`, [`PARALLEL`] at a time; `cancelled` is asked between
    /// chunks.
    ///
    /// # Errors
    /// A failed request or write, or cancellation ([`ObjectsError::Cancelled`]).
    pub fn get_all(
        &self,
        items: &[(String, std::path::PathBuf)],
        cancelled: &(dyn Fn() -> bool + Sync),
    ) -> Result<(), ObjectsError> {
        self.rt.block_on(async {
            let mut s = futures_util::stream::iter(items.iter())
                .map(|(name, to)| self.get(name, to, cancelled))
                .buffer_unordered(PARALLEL);
            while let Some(r) = s.next().await {
                r?;
            }
            Ok(())
        })
    }

    async fn get(
        &self,
        name: &str,
        to: &FsPath,
        cancelled: &(dyn Fn() -> bool + Sync),
    ) -> Result<(), ObjectsError> {
        let r = self
            .s3
            .get(&self.key(name))
            .await
            .map_err(|e| self.err(name, e))?;
        let dir = to.parent().unwrap_or(FsPath::new("."));
        std::fs::create_dir_all(dir).map_err(|e| crate::io::IoError::io(dir, e))?;
        let mut tmp =
            tempfile::NamedTempFile::new_in(dir).map_err(|e| crate::io::IoError::io(dir, e))?;
        let mut body = r.into_stream();
        while let Some(chunk) = body.next().await {
            if cancelled() {
                return Err(ObjectsError::Cancelled);
            }
            let chunk = chunk.map_err(|e| self.err(name, e))?;
            tmp.write_all(&chunk)
                .map_err(|e| crate::io::IoError::io(to, e))?;
        }
        tmp.persist(to)
            .map_err(|e| crate::io::IoError::io(to, e.error))?;
        Ok(())
    }

    /// Uploads the file `from` as `name`; returns false when `mode` is [`Put::Create`] and the
    /// object was already there (nothing was changed).
    ///
    /// # Errors
    /// A failed read or request, or cancellation.
    pub fn put(
        &self,
        name: &str,
        from: &FsPath,
        mode: Put,
        cancelled: &(dyn Fn() -> bool + Sync),
    ) -> Result<bool, ObjectsError> {
        let io = |e| crate::io::IoError::io(from, e);
        let mut f = std::fs::File::open(from).map_err(io)?;
        let len = f.metadata().map_err(io)?.len();
        let key = self.key(name);
        self.rt.block_on(async {
            if len <= SMALL {
                let mut bytes = Vec::with_capacity(len as usize);
                f.read_to_end(&mut bytes).map_err(io)?;
                let opts = PutOptions {
                    mode: match mode {
                        Put::Create => PutMode::Create,
                        Put::Overwrite => PutMode::Overwrite,
                    },
                    ..PutOptions::default()
                };
                return match self.s3.put_opts(&key, PutPayload::from(bytes), opts).await {
                    Ok(_) => Ok(true),
                    Err(object_store::Error::AlreadyExists { .. }) => Ok(false),
                    Err(e) => Err(self.err(name, e)),
                };
            }
            if mode == Put::Create {
                match self.s3.head(&key).await {
                    Ok(m) if m.size == len => return Ok(false),
                    Ok(_) | Err(object_store::Error::NotFound { .. }) => {}
                    Err(e) => return Err(self.err(name, e)),
                }
            }
            let up = self
                .s3
                .put_multipart(&key)
                .await
                .map_err(|e| self.err(name, e))?;
            let mut w = WriteMultipart::new_with_chunk_size(up, CHUNK);
            let mut buf = vec![0u8; CHUNK];
            loop {
                if cancelled() {
                    w.abort().await.map_err(|e| self.err(name, e))?;
                    return Err(ObjectsError::Cancelled);
                }
                let n = f.read(&mut buf).map_err(io)?;
                if n == 0 {
                    break;
                }
                w.wait_for_capacity(PARALLEL)
                    .await
                    .map_err(|e| self.err(name, e))?;
                w.write(&buf[..n]);
            }
            w.finish().await.map_err(|e| self.err(name, e))?;
            Ok(true)
        })
    }
}
