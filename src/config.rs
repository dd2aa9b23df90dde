//! Configuration: embedded defaults (`config/default.toml`), then an optional file (`--config`),
//! then `QEMD_*` environment variables, each overriding the one before (figment). Command-line
//! flags override all of them.

use std::path::{Path, PathBuf};

use bytesize::ByteSize;
use figment::Figment;
use figment::providers::{Env, Format, Toml};
use thiserror::Error;

/// The defaults, compiled in so the binary needs no file at run time.
pub const DEFAULTS: &str = include_str!("../config/default.toml");

/// Every key the configuration knows (also the `QEMD_*` variables read).
pub const KEYS: &[&str] = &["memory_budget", "temp_dir", "outlier_alpha"];

/// Errors of configuration loading.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// The file given with `--config` does not exist.
    #[error("{path}: configuration file not found", path = .0.display())]
    Missing(PathBuf),
    /// A value is malformed or a key unknown.
    #[error("configuration: {0}")]
    Invalid(String),
}

/// The effective configuration.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Memory budget of a denoising run.
    pub memory_budget: ByteSize,
    /// Spill directory; empty for the system temporary directory.
    pub temp_dir: PathBuf,
    /// Outlier threshold in standard deviations.
    pub outlier_alpha: f64,
}

impl Config {
    /// Loads the defaults, then `file`, then the environment.
    ///
    /// # Errors
    /// A missing file, a malformed value, an unknown key.
    pub fn load(file: Option<&Path>) -> Result<Config, ConfigError> {
        let mut fig = Figment::from(Toml::string(DEFAULTS));
        if let Some(f) = file {
            if !f.is_file() {
                return Err(ConfigError::Missing(f.to_path_buf()));
            }
            fig = fig.merge(Toml::file(f));
        }
        fig = fig.merge(Env::prefixed("QEMD_").only(KEYS));
        let c: Config = fig
            .extract()
            .map_err(|e| ConfigError::Invalid(e.to_string()))?;
        if !(c.outlier_alpha.is_finite() && c.outlier_alpha >= 0.0) {
            return Err(ConfigError::Invalid(format!(
                "outlier_alpha must be finite and ≥ 0, got {}",
                c.outlier_alpha
            )));
        }
        Ok(c)
    }

    /// The spill directory, `None` for the system default.
    pub fn temp_dir(&self) -> Option<PathBuf> {
        (!self.temp_dir.as_os_str().is_empty()).then(|| self.temp_dir.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_file_and_unknown_keys() {
        let c = Config::load(None).unwrap();
        assert_eq!(c.memory_budget.as_u64(), 1 << 30);
        assert_eq!(c.temp_dir(), None);
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("c.toml");
        std::fs::write(&f, "memory_budget = \"64 MiB\"\noutlier_alpha = 3.0\n").unwrap();
        let c = Config::load(Some(&f)).unwrap();
        assert_eq!(c.memory_budget.as_u64(), 64 << 20);
        assert_eq!(c.outlier_alpha, 3.0);
        std::fs::write(&f, "memroy_budget = 1\n").unwrap();
        assert!(matches!(
            Config::load(Some(&f)),
            Err(ConfigError::Invalid(_))
        ));
        assert!(matches!(
            Config::load(Some(&dir.path().join("none.toml"))),
            Err(ConfigError::Missing(_))
        ));
    }
}
