//! The SLURM client: `sbatch`, `squeue`, `sacct` and `scancel` run as processes (found on
//! `PATH`, the cluster through the environment's `SLURM_CONF` or `/etc/slurm`), their output
//! parsed. Blocking and free of tokio: the service calls it on the blocking pool. Every command
//! is bounded by [`COMMAND_TIMEOUT`] (killed beyond it), and no output, however malformed, makes
//! it panic: what cannot be read is a [`SlurmError`].

use std::io::Read;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use super::SlurmError;

/// The longest any one SLURM command may take (a busy controller answers within seconds).
pub const COMMAND_TIMEOUT: Duration = Duration::from_secs(30);

/// States a job (array task) does not leave.
pub const TERMINAL: [&str; 11] = [
    "COMPLETED",
    "FAILED",
    "CANCELLED",
    "TIMEOUT",
    "NODE_FAIL",
    "OUT_OF_MEMORY",
    "PREEMPTED",
    "BOOT_FAIL",
    "DEADLINE",
    "SPECIAL_EXIT",
    "REVOKED",
];

/// The terminal states that are not success.
pub fn failed(state: &str) -> bool {
    state != "COMPLETED" && TERMINAL.contains(&state)
}

/// One array job to submit.
#[derive(Debug, Clone, Default)]
pub struct Submit {
    /// `--job-name`.
    pub name: String,
    /// Array tasks (`--array=0-(tasks-1)`), at least 1.
    pub tasks: u64,
    /// Array jobs that must complete first (`--dependency=afterok:…`, with
    /// `--kill-on-invalid-dep=yes`: a task after a failed one is cancelled, not left pending).
    pub after: Vec<String>,
    /// `--chdir`.
    pub chdir: PathBuf,
    /// `--output` (SLURM's `%x`, `%A`, `%a` patterns allowed); standard error goes there too.
    pub output: PathBuf,
    /// `--cpus-per-task`.
    pub cpus_per_task: u32,
    /// `--partition`, when given.
    pub partition: Option<String>,
    /// `--account`, when given.
    pub account: Option<String>,
    /// More options, as given.
    pub extra: Vec<String>,
    /// The program and its arguments (run through `--wrap` as one `exec` line, each word
    /// single-quoted).
    pub command: Vec<String>,
}

impl Submit {
    /// The arguments of `sbatch`.
    pub fn args(&self) -> Vec<String> {
        let mut a = vec![
            "--parsable".to_string(),
            format!("--array=0-{}", self.tasks.max(1) - 1),
            format!("--job-name={}", self.name),
            format!("--cpus-per-task={}", self.cpus_per_task.max(1)),
            format!("--chdir={}", self.chdir.display()),
            format!("--output={}", self.output.display()),
        ];
        if !self.after.is_empty() {
            a.push(format!("--dependency=afterok:{}", self.after.join(":")));
            a.push("--kill-on-invalid-dep=yes".into());
        }
        if let Some(p) = &self.partition {
            a.push(format!("--partition={p}"));
        }
        if let Some(p) = &self.account {
            a.push(format!("--account={p}"));
        }
        a.extend(self.extra.iter().cloned());
        let words: Vec<String> = self.command.iter().map(|w| quote(w)).collect();
        a.push("--wrap".into());
        a.push(format!("exec {}", words.join(" ")));
        a
    }
}

/// `w` single-quoted for `sh` (`'` as `'\''`).
pub fn quote(w: &str) -> String {
    format!("'{}'", w.replace('\'', r"'\''"))
}

/// One array task as `squeue` or `sacct` shows it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TaskState {
    /// The array job's id (what `sbatch` printed).
    pub array: String,
    /// The task's index, or a range (`[1-3]`) for tasks not yet split off.
    pub task: String,
    /// Its state (`PENDING`, `RUNNING`, `COMPLETED`, `FAILED`, …; `sacct`'s `CANCELLED by 0` is
    /// `CANCELLED`).
    pub state: String,
    /// Why it is pending or how it ended (`squeue`'s `%r`; empty from `sacct`).
    pub reason: String,
}

impl TaskState {
    /// `<array>_<task>`, as SLURM names it.
    pub fn id(&self) -> String {
        format!("{}_{}", self.array, self.task)
    }
}

/// Runs SLURM's client commands.
#[derive(Debug, Clone, Default)]
pub struct Client {
    /// A directory holding the commands, else they are looked up on `PATH`.
    pub bin_dir: Option<PathBuf>,
}

/// Collapses `text` to one line of at most 300 characters.
fn one_line(text: &str) -> String {
    let joined = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join("; ");
    match joined.char_indices().nth(300) {
        Some((i, _)) => format!("{}…", &joined[..i]),
        None => joined,
    }
}

/// Reads everything from `r` on a thread (so that a full pipe never blocks the child).
fn drain<R: Read + Send + 'static>(r: Option<R>) -> std::thread::JoinHandle<Vec<u8>> {
    std::thread::spawn(move || {
        let mut buf = Vec::new();
        if let Some(mut r) = r {
            let _ = r.read_to_end(&mut buf);
        }
        buf
    })
}

impl Client {
    fn program(&self, cmd: &str) -> PathBuf {
        match &self.bin_dir {
            Some(d) => d.join(cmd),
            None => PathBuf::from(cmd),
        }
    }

    /// Runs `cmd args`, bounded by `timeout`; its exit success, standard output and error.
    fn output(
        &self,
        cmd: &'static str,
        args: &[String],
        timeout: Duration,
    ) -> Result<(bool, String, String), SlurmError> {
        let mut child = Command::new(self.program(cmd))
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|source| SlurmError::Spawn { cmd, source })?;
        let out = drain(child.stdout.take());
        let err = drain(child.stderr.take());
        let start = Instant::now();
        let status = loop {
            match child.try_wait() {
                Ok(Some(s)) => break s,
                Ok(None) if start.elapsed() < timeout => {
                    std::thread::sleep(Duration::from_millis(10));
                }
                Ok(None) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    return Err(SlurmError::Timeout {
                        cmd,
                        secs: timeout.as_secs(),
                    });
                }
                Err(source) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    return Err(SlurmError::Spawn { cmd, source });
                }
            }
        };
        let text = |h: std::thread::JoinHandle<Vec<u8>>| {
            String::from_utf8_lossy(&h.join().unwrap_or_default()).into_owned()
        };
        Ok((status.success(), text(out), text(err)))
    }

    /// Runs `cmd args`; its standard output, or [`SlurmError::Failed`] with its error output.
    fn run(&self, cmd: &'static str, args: &[String]) -> Result<String, SlurmError> {
        let (ok, out, err) = self.output(cmd, args, COMMAND_TIMEOUT)?;
        if ok {
            Ok(out)
        } else {
            Err(SlurmError::Failed {
                cmd,
                detail: one_line(if err.trim().is_empty() { &out } else { &err }),
            })
        }
    }

    /// Checks that `sbatch` runs (`sbatch --version`); its version line.
    ///
    /// # Errors
    /// The command cannot be run or fails.
    pub fn check(&self) -> Result<String, SlurmError> {
        Ok(one_line(&self.run("sbatch", &["--version".to_string()])?))
    }

    /// Submits an array job; its id.
    ///
    /// # Errors
    /// `sbatch` fails or prints no job id.
    pub fn submit(&self, s: &Submit) -> Result<String, SlurmError> {
        let out = self.run("sbatch", &s.args())?;
        parse_job_id(&out).ok_or_else(|| SlurmError::Output {
            cmd: "sbatch",
            detail: format!("no job id in {:?}", one_line(&out)),
        })
    }

    /// Every array task of the array jobs `ids` that the controller still knows (`squeue -r -t
    /// all`: finished tasks stay for `MinJobAge`, 300 s by default). Jobs it no longer knows are
    /// absent.
    ///
    /// # Errors
    /// `squeue` fails (but for ids the controller does not know) or prints what it should not.
    pub fn states(&self, ids: &[String]) -> Result<Vec<TaskState>, SlurmError> {
        if ids.is_empty() {
            return Ok(Vec::new());
        }
        let args: Vec<String> = [
            "--noheader",
            "--array",
            "--states=all",
            "--format=%F|%K|%T|%r",
        ]
        .iter()
        .map(|s| s.to_string())
        .chain([format!("--jobs={}", ids.join(","))])
        .collect();
        let (ok, out, err) = self.output("squeue", &args, COMMAND_TIMEOUT)?;
        if !ok {
            // Every id unknown (purged): squeue 22.05 says "Invalid job id specified".
            if err.contains("Invalid job id") {
                return Ok(Vec::new());
            }
            return Err(SlurmError::Failed {
                cmd: "squeue",
                detail: one_line(&err),
            });
        }
        parse_squeue(&out)
    }

    /// The final states of the array tasks of `ids` from the accounting database (`sacct`), for
    /// jobs the controller has forgotten.
    ///
    /// # Errors
    /// [`SlurmError::NoAccounting`] when the cluster keeps none; other `sacct` failures.
    pub fn accounting(&self, ids: &[String]) -> Result<Vec<TaskState>, SlurmError> {
        if ids.is_empty() {
            return Ok(Vec::new());
        }
        let args: Vec<String> = ["--noheader", "--parsable2", "--allocations"]
            .iter()
            .map(|s| s.to_string())
            .chain([
                format!("--jobs={}", ids.join(",")),
                "--format=JobID,State".to_string(),
            ])
            .collect();
        let (ok, out, err) = self.output("sacct", &args, COMMAND_TIMEOUT)?;
        if !ok {
            let detail = one_line(&err);
            if err.contains("accounting storage is disabled") {
                return Err(SlurmError::NoAccounting(detail));
            }
            return Err(SlurmError::Failed {
                cmd: "sacct",
                detail,
            });
        }
        parse_sacct(&out)
    }

    /// Cancels the jobs `ids` (whole arrays) and every job named `name` when given; ids that
    /// have ended or are unknown are fine.
    ///
    /// # Errors
    /// `scancel` cannot run or fails for another reason.
    pub fn cancel(&self, ids: &[String], name: Option<&str>) -> Result<(), SlurmError> {
        if !ids.is_empty() {
            let mut args = vec!["--quiet".to_string()];
            args.extend(ids.iter().cloned());
            self.scancel(&args)?;
        }
        if let Some(n) = name {
            self.scancel(&["--quiet".to_string(), format!("--name={n}")])?;
        }
        Ok(())
    }

    fn scancel(&self, args: &[String]) -> Result<(), SlurmError> {
        let (ok, _, err) = self.output("scancel", args, COMMAND_TIMEOUT)?;
        let benign = |l: &str| {
            l.trim().is_empty()
                || l.contains("Invalid job id")
                || l.contains("already completing or completed")
        };
        if ok || err.lines().all(benign) {
            Ok(())
        } else {
            Err(SlurmError::Failed {
                cmd: "scancel",
                detail: one_line(&err),
            })
        }
    }
}

/// The job id `sbatch --parsable` printed (`<id>` or `<id>;<cluster>`).
pub fn parse_job_id(out: &str) -> Option<String> {
    let line = out.lines().map(str::trim).rfind(|l| !l.is_empty())?;
    let id = line.split(';').next()?.trim();
    (!id.is_empty() && id.len() <= 20 && id.bytes().all(|b| b.is_ascii_digit()))
        .then(|| id.to_string())
}

/// A job id as SLURM prints it: digits.
fn is_id(s: &str) -> bool {
    !s.is_empty() && s.len() <= 20 && s.bytes().all(|b| b.is_ascii_digit())
}

/// `squeue --format=%F|%K|%T|%r` lines.
///
/// # Errors
/// [`SlurmError::Output`] for a line that is not four fields with a job id first.
pub fn parse_squeue(out: &str) -> Result<Vec<TaskState>, SlurmError> {
    let mut v = Vec::new();
    for line in out.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let f: Vec<&str> = line.split('|').collect();
        if f.len() != 4 || !is_id(f[0]) || f[2].is_empty() {
            return Err(SlurmError::Output {
                cmd: "squeue",
                detail: format!("unexpected line {:?}", one_line(line)),
            });
        }
        v.push(TaskState {
            array: f[0].to_string(),
            // A job that is not an array shows N/A: task 0 of 1.
            task: if f[1] == "N/A" { "0" } else { f[1] }.to_string(),
            state: f[2].to_string(),
            reason: f[3].to_string(),
        });
    }
    Ok(v)
}

/// `sacct --parsable2 --format=JobID,State` lines (`<array>_<task>|<state>`; a state may read
/// `CANCELLED by 0`).
///
/// # Errors
/// [`SlurmError::Output`] for a line that is not two fields with a job id first.
pub fn parse_sacct(out: &str) -> Result<Vec<TaskState>, SlurmError> {
    let mut v = Vec::new();
    for line in out.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let bad = || SlurmError::Output {
            cmd: "sacct",
            detail: format!("unexpected line {:?}", one_line(line)),
        };
        let (job, state) = line.split_once('|').ok_or_else(bad)?;
        let (array, task) = job.split_once('_').unwrap_or((job, "0"));
        let state = state.split_whitespace().next().ok_or_else(bad)?;
        if !is_id(array) {
            return Err(bad());
        }
        v.push(TaskState {
            array: array.to_string(),
            task: task.to_string(),
            state: state.to_string(),
            reason: String::new(),
        });
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sbatch_arguments_quote_the_command() {
        let s = Submit {
            name: "qemd-x-tiles".into(),
            tasks: 4,
            after: vec!["11".into()],
            chdir: "/d/j".into(),
            output: "/d/j/logs/%x-%A_%a.out".into(),
            cpus_per_task: 2,
            partition: Some("batch".into()),
            account: None,
            extra: vec!["--time=10".into()],
            command: vec!["/opt/q emd".into(), "worker".into(), "it's".into()],
        };
        let a = s.args();
        assert_eq!(a[1], "--array=0-3");
        assert!(a.contains(&"--dependency=afterok:11".to_string()));
        assert!(a.contains(&"--kill-on-invalid-dep=yes".to_string()));
        assert!(a.contains(&"--partition=batch".to_string()));
        assert!(a.contains(&"--time=10".to_string()));
        assert_eq!(a[a.len() - 2], "--wrap");
        assert_eq!(a[a.len() - 1], r"exec '/opt/q emd' 'worker' 'it'\''s'");
        let first = Submit {
            tasks: 0,
            ..Submit::default()
        };
        assert!(first.args().contains(&"--array=0-0".to_string()));
        assert!(!first.args().iter().any(|x| x.starts_with("--dependency")));
    }

    #[test]
    fn outputs_parse_or_fail_without_panicking() {
        assert_eq!(parse_job_id("1234\n").as_deref(), Some("1234"));
        assert_eq!(parse_job_id("77;cluster\n").as_deref(), Some("77"));
        for bad in ["", "\n", "Submitted batch job 5", "12a", ";x"] {
            assert_eq!(parse_job_id(bad), None, "{bad:?}");
        }
        let st = parse_squeue(
            "1|0|COMPLETED|None\n2|[1-3]|PENDING|Dependency\n3|N/A|FAILED|NonZeroExitCode\n\n",
        )
        .unwrap();
        assert_eq!(st.len(), 3);
        assert_eq!(st[1].id(), "2_[1-3]");
        assert_eq!(st[2].task, "0");
        assert!(failed(&st[2].state) && !failed(&st[0].state) && !failed(&st[1].state));
        for bad in [
            "x|0|RUNNING|None",
            "1|0|RUNNING",
            "1||||",
            "1|0||None",
            "\u{0}",
        ] {
            assert!(parse_squeue(bad).is_err(), "{bad:?}");
        }
        let st = parse_sacct("5_0|COMPLETED\n5_1|CANCELLED by 0\n6|FAILED\n").unwrap();
        assert_eq!(st[1].state, "CANCELLED");
        assert_eq!(st[2].id(), "6_0");
        for bad in ["5_0", "x_0|FAILED", "5_0|"] {
            assert!(parse_sacct(bad).is_err(), "{bad:?}");
        }
        let long = "e".repeat(1000);
        assert!(one_line(&format!("a\n\n b \n{long}")).starts_with("a; b; eee"));
        assert!(one_line(&long).chars().count() <= 301);
    }

    #[test]
    fn a_missing_command_is_an_error() {
        let c = Client {
            bin_dir: Some("/nonexistent-qemd-test".into()),
        };
        let e = c.check().unwrap_err().to_string();
        assert!(e.starts_with("sbatch: cannot run"), "{e}");
        assert!(!e.contains('\n'));
    }

    #[test]
    fn commands_are_bounded() {
        let c = Client::default();
        let start = Instant::now();
        let r = c.output("sleep", &["10".to_string()], Duration::from_millis(200));
        assert!(matches!(r, Err(SlurmError::Timeout { .. })), "{r:?}");
        assert!(start.elapsed() < Duration::from_secs(5));
    }
}
