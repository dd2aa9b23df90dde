//! Configuration: embedded defaults (`config/default.toml`), then an optional file (`--config`),
//! then `QEMD_*` environment variables, each overriding the one before (figment). Command-line
//! flags override all of them.

use std::path::{Path, PathBuf};
use std::time::Duration;

use bytesize::ByteSize;
use figment::Figment;
use figment::providers::{Env, Format, Toml};
use thiserror::Error;

pub use crate::pipeline::scaleout::Executor;

/// The defaults, compiled in so the binary needs no file at run time.
pub const DEFAULTS: &str = include_str!("../config/default.toml");

/// Every key the configuration knows (also the `QEMD_*` variables read).
pub const KEYS: &[&str] = &[
    "memory_budget",
    "temp_dir",
    "outlier_alpha",
    "listen",
    "data_dir",
    "auth_tokens",
    "max_upload_size",
    "max_sync_size",
    "job_concurrency",
    "queue_capacity",
    "job_tile_points",
    "sync_concurrency",
    "preview_points",
    "job_time_limit",
    "sync_time_limit",
    "header_read_timeout",
    "body_read_timeout",
    "max_connections_per_address",
    "log_format",
    "log_level",
    "executor",
    "slurm_min_points",
    "slurm_worker",
    "slurm_partition",
    "slurm_account",
    "slurm_cpus_per_task",
    "slurm_max_tasks",
    "slurm_sbatch_args",
    "slurm_poll_interval",
];

/// Options of `slurm_sbatch_args` the service sets itself for each phase's array job.
const SBATCH_OWN: &[&str] = &[
    "--array",
    "-a",
    "--dependency",
    "-d",
    "--wrap",
    "--parsable",
    "--job-name",
    "-J",
    "--output",
    "-o",
    "--error",
    "-e",
    "--chdir",
    "-D",
    "--cpus-per-task",
    "-c",
    "--kill-on-invalid-dep",
];

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
    /// `serve`: address to listen on (`host:port`).
    pub listen: String,
    /// `serve`: job database, uploads, results and checkpoints.
    pub data_dir: PathBuf,
    /// `serve`: comma-separated `token:tenant` pairs; empty for no authentication.
    pub auth_tokens: String,
    /// `serve`: largest upload.
    pub max_upload_size: ByteSize,
    /// `serve`: largest synchronous request body.
    pub max_sync_size: ByteSize,
    /// `serve`: jobs running at the same time.
    pub job_concurrency: usize,
    /// `serve`: accepted jobs waiting for a slot.
    pub queue_capacity: usize,
    /// `serve`: point clouds larger than this run tiled with tiles of about this many points.
    pub job_tile_points: u64,
    /// `serve`: synchronous requests running at the same time.
    pub sync_concurrency: usize,
    /// `serve`: most points on each side of a job's before/after preview (the web viewer).
    pub preview_points: u64,
    /// `serve`: wall-clock limit of one run of a job (`6h`, `90m`; a bare number is seconds).
    #[serde(with = "duration")]
    pub job_time_limit: Duration,
    /// `serve`: wall-clock limit of a synchronous request.
    #[serde(with = "duration")]
    pub sync_time_limit: Duration,
    /// `serve`: time a connection has to send a request's headers.
    #[serde(with = "duration")]
    pub header_read_timeout: Duration,
    /// `serve`: longest stall of a request body between chunks.
    #[serde(with = "duration")]
    pub body_read_timeout: Duration,
    /// `serve`: connections open at once from one client address.
    pub max_connections_per_address: usize,
    /// `serve`: log line format.
    pub log_format: LogFormat,
    /// `serve`: log filter (tracing `EnvFilter` syntax).
    pub log_level: String,
    /// `serve`: where jobs run: `local`, or `slurm` for point clouds of at least
    /// `slurm_min_points` points (docs/SCALE-OUT.md, "The service on SLURM").
    pub executor: Executor,
    /// `serve` with `executor = "slurm"`: clouds with at least this many points go to SLURM.
    pub slurm_min_points: u64,
    /// `serve` with SLURM: the `qemd` binary as the cluster's nodes see it; empty for the
    /// service's own executable.
    pub slurm_worker: PathBuf,
    /// `serve` with SLURM: `sbatch --partition`; empty for the cluster's default.
    pub slurm_partition: String,
    /// `serve` with SLURM: `sbatch --account`; empty for the user's default.
    pub slurm_account: String,
    /// `serve` with SLURM: `sbatch --cpus-per-task`, also each worker's `--threads`.
    pub slurm_cpus_per_task: u32,
    /// `serve` with SLURM: most array tasks of one phase (each takes its share of the tiles).
    pub slurm_max_tasks: u64,
    /// `serve` with SLURM: more `sbatch` options, separated by white space (no quoting).
    pub slurm_sbatch_args: String,
    /// `serve` with SLURM: how often a job's SLURM jobs and checkpoints are looked at.
    #[serde(with = "duration")]
    pub slurm_poll_interval: Duration,
}

/// How `qemd serve` writes its log lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line.
    Json,
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
        crate::pipeline::validate_alpha(c.outlier_alpha)
            .map_err(|e| ConfigError::Invalid(e.to_string()))?;
        c.validate_service()?;
        Ok(c)
    }

    /// Checks the keys of `qemd serve` (ranges, token syntax).
    ///
    /// # Errors
    /// [`ConfigError::Invalid`] naming the key.
    pub fn validate_service(&self) -> Result<(), ConfigError> {
        let bad = |key: &str, detail: &str| Err(ConfigError::Invalid(format!("{key} {detail}")));
        if self.listen.trim().is_empty() || !self.listen.contains(':') {
            return bad("listen", "must be host:port");
        }
        if self.data_dir.as_os_str().is_empty() {
            return bad("data_dir", "must not be empty");
        }
        if !(1..=256).contains(&self.job_concurrency) {
            return bad("job_concurrency", "must be between 1 and 256");
        }
        if !(1..=1_000_000).contains(&self.queue_capacity) {
            return bad("queue_capacity", "must be between 1 and 1000000");
        }
        if !(1..=1_000_000).contains(&self.max_connections_per_address) {
            return bad(
                "max_connections_per_address",
                "must be between 1 and 1000000",
            );
        }
        if !(1..=4096).contains(&self.sync_concurrency) {
            return bad("sync_concurrency", "must be between 1 and 4096");
        }
        if !(1000..=20_000_000).contains(&self.preview_points) {
            return bad("preview_points", "must be between 1000 and 20000000");
        }
        if self.job_tile_points < 1000 {
            return bad("job_tile_points", "must be at least 1000");
        }
        let limits = Duration::from_secs(1)..=Duration::from_secs(365 * 86_400);
        for (key, limit) in [
            ("job_time_limit", self.job_time_limit),
            ("sync_time_limit", self.sync_time_limit),
            ("header_read_timeout", self.header_read_timeout),
            ("body_read_timeout", self.body_read_timeout),
        ] {
            if !limits.contains(&limit) {
                return bad(key, "must be between 1s and 365days");
            }
        }
        if self.max_upload_size.as_u64() == 0 || self.max_sync_size.as_u64() == 0 {
            return bad("max_upload_size and max_sync_size", "must be positive");
        }
        self.tokens()?;
        self.validate_slurm()
    }

    /// Checks the `slurm_*` keys (whatever the executor, so that a file switched to SLURM later
    /// holds no surprise).
    ///
    /// # Errors
    /// [`ConfigError::Invalid`] naming the key.
    fn validate_slurm(&self) -> Result<(), ConfigError> {
        let bad = |key: &str, detail: &str| Err(ConfigError::Invalid(format!("{key} {detail}")));
        if self.slurm_min_points == 0 {
            return bad("slurm_min_points", "must be at least 1");
        }
        if !self.slurm_worker.as_os_str().is_empty() && !self.slurm_worker.is_absolute() {
            return bad(
                "slurm_worker",
                "must be an absolute path (as the cluster's nodes see it), or empty",
            );
        }
        for (key, v) in [
            ("slurm_partition", &self.slurm_partition),
            ("slurm_account", &self.slurm_account),
        ] {
            if v.chars()
                .any(|c| c.is_whitespace() || c.is_control() || c == ',')
            {
                return bad(key, "must be one name (no white space or commas), or empty");
            }
        }
        if !(1..=4096).contains(&self.slurm_cpus_per_task) {
            return bad("slurm_cpus_per_task", "must be between 1 and 4096");
        }
        if !(1..=1_000_000).contains(&self.slurm_max_tasks) {
            return bad("slurm_max_tasks", "must be between 1 and 1000000");
        }
        let limits = Duration::from_millis(100)..=Duration::from_secs(600);
        if !limits.contains(&self.slurm_poll_interval) {
            return bad("slurm_poll_interval", "must be between 100ms and 10m");
        }
        for arg in self.sbatch_args() {
            let name = arg.split_once('=').map_or(arg.as_str(), |(n, _)| n);
            let short = SBATCH_OWN
                .iter()
                .any(|o| o.len() == 2 && name.starts_with(o) && !name.starts_with("--"));
            if SBATCH_OWN.contains(&name) || short {
                return Err(ConfigError::Invalid(format!(
                    "slurm_sbatch_args: {arg} is set by the service for each phase"
                )));
            }
        }
        Ok(())
    }

    /// The words of `slurm_sbatch_args`.
    pub fn sbatch_args(&self) -> Vec<String> {
        self.slurm_sbatch_args
            .split_whitespace()
            .map(str::to_string)
            .collect()
    }

    /// The bearer tokens and their tenants from `auth_tokens` (empty: no authentication).
    ///
    /// # Errors
    /// An entry that is not `token:tenant`, a tenant with characters other than letters, digits,
    /// `-` and `_`, or a token given twice.
    pub fn tokens(&self) -> Result<Vec<(String, String)>, ConfigError> {
        let mut out: Vec<(String, String)> = Vec::new();
        for entry in self.auth_tokens.split(',').map(str::trim) {
            if entry.is_empty() {
                continue;
            }
            let bad = |d: &str| ConfigError::Invalid(format!("auth_tokens: {d}"));
            let (token, tenant) = entry
                .rsplit_once(':')
                .ok_or_else(|| bad("each entry must be token:tenant"))?;
            let (token, tenant) = (token.trim(), tenant.trim());
            if token.len() < 8 || token.chars().any(|c| c.is_whitespace() || c.is_control()) {
                return Err(bad(
                    "a token must have at least 8 characters and no white space",
                ));
            }
            let ok = |c: char| c.is_ascii_alphanumeric() || c == '-' || c == '_';
            if tenant.is_empty() || tenant.len() > 64 || !tenant.chars().all(ok) {
                return Err(bad("a tenant must be 1 to 64 letters, digits, '-' or '_'"));
            }
            if out.iter().any(|(t, _)| t == token) {
                return Err(bad("a token is given twice"));
            }
            out.push((token.to_string(), tenant.to_string()));
        }
        Ok(out)
    }

    /// The spill directory, `None` for the system default.
    pub fn temp_dir(&self) -> Option<PathBuf> {
        (!self.temp_dir.as_os_str().is_empty()).then(|| self.temp_dir.clone())
    }
}

/// Durations as people write them (`6h`, `1m 30s`, humantime's syntax), or a number of seconds.
mod duration {
    use std::time::Duration;

    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&humantime::format_duration(*d).to_string())
    }

    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Text {
        Seconds(u64),
        Human(String),
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Duration, D::Error> {
        match Text::deserialize(d)? {
            Text::Seconds(s) => Ok(Duration::from_secs(s)),
            Text::Human(h) => humantime::parse_duration(h.trim()).map_err(|e| {
                serde::de::Error::custom(format!("`{h}` is not a duration like 90s or 6h: {e}"))
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issue10_outlier_alpha_has_one_default() {
        // The embedded configuration, the service's settings and a library job agree (they
        // said 2, 2 and 1 before the spec).
        let want = crate::pipeline::DEFAULT_OUTLIER_ALPHA;
        assert_eq!(Config::load(None).unwrap().outlier_alpha, want);
        assert_eq!(crate::jobs::Settings::default().outlier_alpha, want);
        assert_eq!(crate::pipeline::Job::new("a", "b").spec.outlier_alpha, want);
    }

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
        std::fs::write(&f, "outlier_alpha = -1.0\n").unwrap();
        assert!(matches!(
            Config::load(Some(&f)),
            Err(ConfigError::Invalid(m)) if m.contains("outlier_alpha")
        ));
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

    #[test]
    fn issue15_time_limits_parse_as_durations() {
        let c = Config::load(None).unwrap();
        assert_eq!(c.job_time_limit, crate::jobs::JOB_TIME_LIMIT);
        assert_eq!(c.sync_time_limit, crate::jobs::SYNC_TIME_LIMIT);
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("c.toml");
        std::fs::write(&f, "job_time_limit = \"1h 30m\"\nsync_time_limit = 5\n").unwrap();
        let c = Config::load(Some(&f)).unwrap();
        assert_eq!(c.job_time_limit, Duration::from_secs(5400));
        assert_eq!(c.sync_time_limit, Duration::from_secs(5));
        std::fs::write(&f, "sync_time_limit = \"5 parsecs\"\n").unwrap();
        assert!(matches!(
            Config::load(Some(&f)),
            Err(ConfigError::Invalid(m)) if m.contains("sync_time_limit") && m.contains("5 parsecs")
        ));
    }

    #[test]
    fn service_keys_and_tokens() {
        let c = Config::load(None).unwrap();
        assert_eq!(c.listen, "127.0.0.1:8080");
        assert_eq!(c.log_format, LogFormat::Text);
        assert!(c.tokens().unwrap().is_empty());
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("c.toml");
        std::fs::write(
            &f,
            "auth_tokens = \"secret-aaa:alice, secret-bbb:bob\"\nlog_format = \"json\"\n",
        )
        .unwrap();
        let c = Config::load(Some(&f)).unwrap();
        assert_eq!(
            c.tokens().unwrap(),
            vec![
                ("secret-aaa".to_string(), "alice".to_string()),
                ("secret-bbb".to_string(), "bob".to_string())
            ]
        );
        assert_eq!(c.log_format, LogFormat::Json);
        for bad in [
            "auth_tokens = \"nocolon\"",
            "auth_tokens = \"short:a\"",
            "auth_tokens = \"secret-aaa:a b\"",
            "auth_tokens = \"secret-aaa:a,secret-aaa:b\"",
            "job_concurrency = 0",
            "log_format = \"xml\"",
            "listen = \"8080\"",
            "job_time_limit = \"0s\"",
            "sync_time_limit = \"soon\"",
        ] {
            std::fs::write(&f, bad).unwrap();
            assert!(Config::load(Some(&f)).is_err(), "{bad}");
        }
    }
    #[test]
    fn issue11_executor_and_slurm_keys() {
        let c = Config::load(None).unwrap();
        assert_eq!(c.executor, Executor::Local);
        assert_eq!(c.slurm_min_points, 20_000_000);
        assert_eq!(c.slurm_poll_interval, Duration::from_secs(5));
        assert!(c.sbatch_args().is_empty());
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("c.toml");
        std::fs::write(
            &f,
            "executor = \"slurm\"\nslurm_min_points = 1000\nslurm_worker = \"/opt/qemd\"\n\
             slurm_partition = \"batch\"\nslurm_cpus_per_task = 2\nslurm_max_tasks = 8\n\
             slurm_sbatch_args = \"--time=2:00:00  --mem=6G\"\nslurm_poll_interval = \"250ms\"\n",
        )
        .unwrap();
        let c = Config::load(Some(&f)).unwrap();
        assert_eq!(c.executor, Executor::Slurm);
        assert_eq!(c.slurm_min_points, 1000);
        assert_eq!(c.slurm_worker, PathBuf::from("/opt/qemd"));
        assert_eq!(c.slurm_partition, "batch");
        assert_eq!((c.slurm_cpus_per_task, c.slurm_max_tasks), (2, 8));
        assert_eq!(c.sbatch_args(), vec!["--time=2:00:00", "--mem=6G"]);
        assert_eq!(c.slurm_poll_interval, Duration::from_millis(250));
        // Each bad value is refused, naming its key.
        for (bad, key) in [
            ("executor = \"kubernetes\"", "executor"),
            ("slurm_min_points = 0", "slurm_min_points"),
            ("slurm_min_points = -5", "slurm_min_points"),
            ("slurm_worker = \"qemd\"", "slurm_worker"),
            ("slurm_partition = \"a b\"", "slurm_partition"),
            ("slurm_account = \"a,b\"", "slurm_account"),
            ("slurm_cpus_per_task = 0", "slurm_cpus_per_task"),
            ("slurm_max_tasks = 0", "slurm_max_tasks"),
            ("slurm_poll_interval = \"10ms\"", "slurm_poll_interval"),
            ("slurm_poll_interval = \"1h\"", "slurm_poll_interval"),
            ("slurm_sbatch_args = \"--array=0-9\"", "--array"),
            (
                "slurm_sbatch_args = \"--time=5 --dependency=afterok:1\"",
                "--dependency",
            ),
            ("slurm_sbatch_args = \"-J name\"", "-J"),
            ("slurm_sbatch_args = \"-c4\"", "-c4"),
            ("slurm_sbatch_args = \"--output=/tmp/x\"", "--output"),
        ] {
            std::fs::write(&f, bad).unwrap();
            match Config::load(Some(&f)) {
                Err(ConfigError::Invalid(m)) => assert!(m.contains(key), "{bad}: {m}"),
                other => panic!("{bad}: {other:?}"),
            }
        }
        // Options the service does not set pass, short ones included.
        std::fs::write(&f, "slurm_sbatch_args = \"-A acct -t 10 --qos=low\"").unwrap();
        assert!(Config::load(Some(&f)).is_ok());
    }
}
