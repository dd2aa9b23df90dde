//! The address of a work directory: a local path, or a `file://` URL (`file:///abs/path`).
//! Object stores (`s3://bucket/prefix`) are refused with a message until they are supported.

use std::path::{Path, PathBuf};

use super::ScaleoutError;

/// Where a scale-out job keeps its files.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WorkUrl {
    /// A directory on a file system every task can reach (absolute).
    Local(PathBuf),
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
            "s3" | "gs" | "az" | "azure" => Err(bad(
                "object-store work directories are not supported yet; use a shared file system \
                 path or file:// URL",
            )),
            _ => Err(bad("unknown scheme (expected a path or file:///abs/path)")),
        }
    }

    /// The local directory.
    pub fn path(&self) -> &Path {
        match self {
            WorkUrl::Local(p) => p,
        }
    }
}

impl std::fmt::Display for WorkUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            WorkUrl::Local(p) => write!(f, "{}", p.display()),
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
        assert!(rel.path().is_absolute() && rel.path().ends_with("rel/w"));
        for bad in [
            "",
            "file://host/x",
            "file://x",
            "s3://b/p",
            "http://x/y",
            "file:///a%2",
        ] {
            let e = WorkUrl::parse(bad).unwrap_err().to_string();
            assert_eq!(e.lines().count(), 1, "{e}");
            assert!(e.starts_with(bad), "{e}");
        }
    }
}
