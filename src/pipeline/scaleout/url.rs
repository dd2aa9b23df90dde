//! The address of a work directory: a local path, a `file://` URL (`file:///abs/path`), or an S3
//! prefix (`s3://bucket/prefix`). The pipeline runs on local directories only; an S3 work
//! directory is mirrored into local scratch by the object-store layer (`crate::objects`, feature
//! `s3`), which hands the pipeline the scratch directory. Other object stores (`gs://`, `az://`)
//! are refused with a message.

use std::path::{Path, PathBuf};

use super::ScaleoutError;

/// Where a scale-out job keeps its files.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WorkUrl {
    /// A directory on a file system every task can reach (absolute).
    Local(PathBuf),
    /// A prefix in an S3 bucket (endpoint and credentials from the `AWS_*` environment).
    S3 {
        /// The bucket.
        bucket: String,
        /// The key prefix, without leading or trailing `/` (may be empty).
        prefix: String,
    },
}

impl WorkUrl {
    /// Parses `--work`: a plain path (made absolute against the current directory) or
    /// `file://[localhost]/abs/path` (percent-escapes decoded).
    ///
    /// # Errors
    /// [`ScaleoutError::Url`] for another scheme, a remote host or a malformed escape.
    pub fn parse(text: &str) -> Result<WorkUrl, ScaleoutError> {
        let bad = |detail: &str| ScaleoutError::Url {
            url: text.to_string(),
            detail: detail.to_string(),
        };
        if text.is_empty() {
            return Err(bad("empty work directory"));
        }
        let Some((scheme, rest)) = text.split_once("://") else {
            let p = Path::new(text);
            let abs = if p.is_absolute() {
                p.to_path_buf()
            } else {
                std::env::current_dir()
                    .map_err(|e| bad(&format!("cannot tell the current directory: {e}")))?
                    .join(p)
            };
            return Ok(WorkUrl::Local(abs));
        };
        match scheme.to_ascii_lowercase().as_str() {
            "file" => {
                let path = rest.strip_prefix("localhost").unwrap_or(rest);
                if !path.starts_with('/') {
                    return Err(bad(
                        "a file URL names a local absolute path: file:///abs/path",
                    ));
                }
                let decoded = percent_decode(path).ok_or_else(|| bad("malformed %-escape"))?;
                Ok(WorkUrl::Local(PathBuf::from(decoded)))
            }
            "s3" => {
                let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
                let valid =
                    |c: char| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.';
                if bucket.len() < 3 || bucket.len() > 63 || !bucket.chars().all(valid) {
                    return Err(bad(
                        "an S3 work directory is s3://bucket/prefix, with a bucket name of 3 to 63 \
                         lower-case letters, digits, '-' or '.'",
                    ));
                }
                let prefix = prefix.trim_matches('/');
                if prefix.split('/').any(|s| s == "." || s == "..") || prefix.contains("//") {
                    return Err(bad("an S3 prefix has no empty, '.' or '..' segments"));
                }
                Ok(WorkUrl::S3 {
                    bucket: bucket.to_string(),
                    prefix: prefix.to_string(),
                })
            }
            "gs" | "az" | "azure" => Err(bad(
                "only S3 object stores are built in (s3://bucket/prefix); use S3, a shared file \
                 system path or a file:// URL",
            )),
            _ => Err(bad("unknown scheme (expected a path or file:///abs/path)")),
        }
    }

    /// The local directory.
    ///
    /// # Errors
    /// [`ScaleoutError::Url`] for an object store: the pipeline runs on its local mirror
    /// (`crate::objects`).
    pub fn local(&self) -> Result<&Path, ScaleoutError> {
        match self {
            WorkUrl::Local(p) => Ok(p),
            WorkUrl::S3 { .. } => Err(ScaleoutError::Url {
                url: self.to_string(),
                detail: "an object-store work directory is run through its local mirror (a build \
                         with the `s3` feature)"
                    .into(),
            }),
        }
    }
}

impl std::fmt::Display for WorkUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            WorkUrl::Local(p) => write!(f, "{}", p.display()),
            WorkUrl::S3 { bucket, prefix } if prefix.is_empty() => write!(f, "s3://{bucket}"),
            WorkUrl::S3 { bucket, prefix } => write!(f, "s3://{bucket}/{prefix}"),
        }
    }
}

/// Decodes `%XX` escapes (UTF-8 after decoding); `None` for a malformed escape or bytes that are
/// not UTF-8.
fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = s.get(i + 1..i + 3)?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_and_file_urls_name_local_directories() {
        assert_eq!(
            WorkUrl::parse("file:///data/job%201").unwrap(),
            WorkUrl::Local("/data/job 1".into())
        );
        assert_eq!(
            WorkUrl::parse("file://localhost/data/j").unwrap(),
            WorkUrl::Local("/data/j".into())
        );
        assert_eq!(
            WorkUrl::parse("/abs/w").unwrap(),
            WorkUrl::Local("/abs/w".into())
        );
        let rel = WorkUrl::parse("rel/w").unwrap();
        let rel = rel.local().unwrap();
        assert!(rel.is_absolute() && rel.ends_with("rel/w"));
        let s3 = WorkUrl::parse("s3://my-bucket/jobs/a/").unwrap();
        assert_eq!(
            s3,
            WorkUrl::S3 {
                bucket: "my-bucket".into(),
                prefix: "jobs/a".into()
            }
        );
        assert_eq!(s3.to_string(), "s3://my-bucket/jobs/a");
        assert!(s3.local().is_err());
        assert_eq!(WorkUrl::parse("s3://bkt").unwrap().to_string(), "s3://bkt");
        for bad in [
            "",
            "file://host/x",
            "file://x",
            "s3://b/p",
            "s3://Big/p",
            "s3://bkt/a/../b",
            "s3://bkt/a//b",
            "gs://b/p",
            "http://x/y",
            "file:///a%2",
        ] {
            let e = WorkUrl::parse(bad).unwrap_err().to_string();
            assert_eq!(e.lines().count(), 1, "{e}");
            assert!(e.starts_with(bad), "{e}");
        }
    }
}
