//! Issue 11 §3: `qemd serve` with `executor = "slurm"` on the real single-node cluster
//! (`.ci/slurm.sh start`). The real server on `127.0.0.1:0` plans a job above
//! `slurm_min_points` into its work directory and submits each phase as an array job; the tests
//! check over HTTP that the job says where it ran, that its SLURM jobs really ran (squeue knows
//! them by the service's job name), and that the result has the bytes of `qemd denoise`; that
//! `DELETE` cancels the SLURM jobs; and that a server killed mid-job re-attaches to the jobs it
//! submitted when it starts again on the same data directory.

use std::path::Path;
use std::time::{Duration, Instant};

use reqwest::StatusCode;
use reqwest::blocking::Client;
use serde_json::{Value, json};

use super::{Cluster, TERMINAL, TIMEOUT, parse_states};
use crate::server::{
    Server, cli, client, download, json_of, post_job, sha256_hex, upload, wait, wait_for,
    write_cloud,
};

/// The service's configuration: clouds of at least 50 000 points go to SLURM in tiles of
/// `tile` points, at most 2 tasks a phase, looked at 5 times a second.
fn config(tile: u64) -> String {
    format!(
        "job_tile_points = {tile}\nexecutor = \"slurm\"\nslurm_min_points = 50000\n\
         slurm_cpus_per_task = 1\nslurm_max_tasks = 2\nslurm_poll_interval = \"200ms\"\n"
    )
}

/// Every array task SLURM still knows under the service's job name of job `id`:
/// (`<job>_<task>`, state, reason).
fn named(c: &Cluster, id: &str) -> Vec<(String, String, String)> {
    let name = format!("--name=qemd-{id}");
    let out = c.run(
        "squeue",
        &["-h", "-r", "-t", "all", "-o", "%i|%T|%r", &name],
    );
    parse_states(&out)
}

/// Cancels whatever SLURM jobs of the service's job `id` are left when a test ends (a failed
/// test leaves nothing queued).
struct Leftovers {
    c: Cluster,
    ids: Vec<String>,
}

impl Drop for Leftovers {
    fn drop(&mut self) {
        for id in &self.ids {
            let _ = self
                .c
                .cmd("scancel")
                .args(["--quiet", &format!("--name=qemd-{id}")])
                .status();
        }
    }
}

/// The recorded array jobs of a job view: (phase, SLURM id, tasks).
fn recorded(v: &Value) -> Vec<(String, String, u64)> {
    v["slurm"]["jobs"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|j| {
                    (
                        j["phase"].as_str().unwrap_or_default().to_string(),
                        j["id"].as_str().unwrap_or_default().to_string(),
                        j["tasks"].as_u64().unwrap_or(0),
                    )
                })
                .collect()
        })
        .unwrap_or_default()
}

/// Starts a SLURM-configured server in `dir`, uploads a generated cloud of `points` points and
/// submits a job on it: the server, the job id and the input's path.
fn start_job(dir: &Path, tile: u64, points: usize, c: &Client) -> (Server, String) {
    let conf = Cluster::get().conf;
    let s = Server::start(
        dir,
        &config(tile),
        &[("SLURM_CONF", conf.to_str().unwrap())],
    );
    let path = dir.join("in.ply");
    write_cloud(&path, points, 11);
    let up = upload(c, &s, "", std::fs::read(&path).unwrap());
    let (status, _, v) = post_job(c, &s, &json!({"input": up["id"]}));
    assert_eq!(status, StatusCode::CREATED, "{v}");
    assert_eq!(v["executor"], "slurm", "{v}");
    (s, v["id"].as_str().unwrap().to_string())
}

/// Waits until the job's four phases are recorded as submitted and a task of it runs on the
/// cluster; the job's view then.
fn wait_submitted_and_running(c: &Client, s: &Server, cl: &Cluster, id: &str) -> Value {
    let v = wait_for(c, s, id, "submitted to SLURM", |v| {
        !matches!(v["status"].as_str(), Some("accepted" | "running")) || recorded(v).len() == 4
    });
    assert_eq!(v["status"], "running", "{v}\nlog:\n{}", s.log());
    let start = Instant::now();
    loop {
        let st = named(cl, id);
        if st.iter().any(|t| t.1 == "RUNNING") {
            return v;
        }
        assert!(
            start.elapsed() < TIMEOUT,
            "no task of job {id} runs: {st:?}\nlog:\n{}",
            s.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Committed tile checkpoints in the job's work directory.
fn tile_checkpoints(s: &Server, id: &str) -> usize {
    crate::server::tile_checkpoints(&s.data.join("jobs").join(id).join("work"))
}

#[test]
#[ignore = "needs SLURM (.ci/run starts it)"]
fn issue11_service_job_on_slurm_downloads_the_denoise_bytes() {
    let d = tempfile::tempdir().unwrap();
    let c = client();
    let cl = Cluster::get();
    let (s, id) = start_job(d.path(), 20_000, 200_000, &c);
    let _left = Leftovers {
        c: Cluster::get(),
        ids: vec![id.clone()],
    };
    // A small job on the same server stays local, and is not held up by the one on SLURM.
    let small = d.path().join("small.ply");
    write_cloud(&small, 5_000, 12);
    let up = upload(&c, &s, "", std::fs::read(&small).unwrap());
    let (status, _, v) = post_job(&c, &s, &json!({"input": up["id"]}));
    assert_eq!(status, StatusCode::CREATED, "{v}");
    let small_id = v["id"].as_str().unwrap().to_string();

    // Progress comes from the committed checkpoints: the phases are named as the scale-out
    // phases while the job runs on the cluster.
    let mut phases_seen: Vec<String> = Vec::new();
    let start = Instant::now();
    let done = loop {
        let v = crate::server::job(&c, &s, &id);
        if !matches!(v["status"].as_str(), Some("accepted" | "running")) {
            break v;
        }
        if let Some(p) = v["progress"]["phase"].as_str()
            && phases_seen.last().map(String::as_str) != Some(p)
        {
            phases_seen.push(p.to_string());
        }
        assert!(start.elapsed() < TIMEOUT, "job {id} never finished");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(done["status"], "successful", "{done}\nlog:\n{}", s.log());
    assert!(
        phases_seen
            .iter()
            .any(|p| ["partition", "globals", "tiles", "stitch"].contains(&p.as_str())),
        "{phases_seen:?}"
    );

    // Where it ran: every phase as an array job, under the service's job name, all completed.
    assert_eq!(done["executor"], "slurm", "{done}");
    let jobs = recorded(&done);
    let phases: Vec<&str> = jobs.iter().map(|j| j.0.as_str()).collect();
    assert_eq!(
        phases,
        ["partition", "globals", "tiles", "stitch"],
        "{done}"
    );
    assert_eq!(jobs[2].2, 2, "tiles in arrays of slurm_max_tasks: {done}");
    assert_eq!(done["slurm"]["resubmits"], 0, "{done}");
    assert!(done["report"]["tiles"].as_u64().unwrap() > 2, "{done}");
    // A task whose commit the service saw may still be COMPLETING (SLURM's clean-up after the
    // step ends, seconds on a loaded machine): wait for the final states, boundedly.
    let mut tasks = named(&cl, &id);
    for _ in 0..120 {
        if tasks.iter().all(|t| t.1 != "COMPLETING") {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(250));
        tasks = named(&cl, &id);
    }
    let ids: Vec<&str> = jobs.iter().map(|j| j.1.as_str()).collect();
    assert_eq!(
        tasks.len() as u64,
        jobs.iter().map(|j| j.2).sum::<u64>(),
        "{tasks:?}"
    );
    for t in &tasks {
        assert_eq!(t.1, "COMPLETED", "{tasks:?}");
        let array = t.0.split('_').next().unwrap();
        assert!(ids.contains(&array), "{t:?} not recorded in {ids:?}");
    }

    // The bytes of `qemd denoise` with the same (default) flags.
    let bytes = download(&c, &s, &id);
    assert_eq!(done["result"]["sha256"], sha256_hex(&bytes));
    let want = cli(&d.path().join("in.ply"), &d.path().join("cli.ply"), &[]);
    assert!(
        bytes == want,
        "the SLURM job's bytes differ from qemd denoise"
    );
    assert!(
        !s.data.join("jobs").join(&id).join("logs").exists(),
        "the task logs go after success"
    );

    let small_done = wait(&c, &s, &small_id);
    assert_eq!(small_done["status"], "successful", "{small_done}");
    assert_eq!(small_done["executor"], "local");
    assert!(small_done["slurm"].is_null(), "{small_done}");
    assert!(named(&cl, &small_id).is_empty());
    let small_want = cli(&small, &d.path().join("small-cli.ply"), &[]);
    assert!(download(&c, &s, &small_id) == small_want);
}

#[test]
#[ignore = "needs SLURM (.ci/run starts it)"]
fn issue11_service_delete_cancels_the_slurm_jobs() {
    let d = tempfile::tempdir().unwrap();
    let c = client();
    let cl = Cluster::get();
    let (s, id) = start_job(d.path(), 8_000, 300_000, &c);
    let _left = Leftovers {
        c: Cluster::get(),
        ids: vec![id.clone()],
    };
    let v = wait_submitted_and_running(&c, &s, &cl, &id);
    let jobs = recorded(&v);
    let before = named(&cl, &id);
    assert!(
        before.iter().any(|t| !TERMINAL.contains(&t.1.as_str())),
        "{before:?}"
    );

    let (status, _, v) = json_of(c.delete(s.url(&format!("/v1/jobs/{id}"))).send().unwrap());
    assert_eq!(status, StatusCode::OK, "{v}");
    assert_eq!(v["status"], "dismissed", "{v}");

    // scancel: every task of the job ends, the stitch never runs.
    let start = Instant::now();
    let after = loop {
        let st = named(&cl, &id);
        if st.iter().all(|t| TERMINAL.contains(&t.1.as_str())) {
            break st;
        }
        assert!(start.elapsed() < TIMEOUT, "tasks still alive: {st:?}");
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(after.iter().any(|t| t.1 == "CANCELLED"), "{after:?}");
    let stitch = &jobs.iter().find(|j| j.0 == "stitch").unwrap().1;
    for t in after
        .iter()
        .filter(|t| t.0.starts_with(&format!("{stitch}_")))
    {
        assert_eq!(t.1, "CANCELLED", "the stitch ran: {after:?}");
    }
    assert!(s.log().contains("SLURM jobs cancelled"), "{}", s.log());

    // Dismissed for good: no result, and the files go once the tasks are gone.
    assert_eq!(crate::server::job(&c, &s, &id)["status"], "dismissed");
    assert_eq!(
        c.get(s.url(&format!("/v1/jobs/{id}/result")))
            .send()
            .unwrap()
            .status(),
        StatusCode::NOT_FOUND
    );
    let dir = s.data.join("jobs").join(&id);
    let start = Instant::now();
    while dir.exists() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "{} left behind",
            dir.display()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
#[ignore = "needs SLURM (.ci/run starts it)"]
fn issue11_service_restarted_mid_job_reattaches_to_its_slurm_jobs() {
    let d = tempfile::tempdir().unwrap();
    let c = client();
    let cl = Cluster::get();
    let (mut s, id) = start_job(d.path(), 8_000, 300_000, &c);
    let _left = Leftovers {
        c: Cluster::get(),
        ids: vec![id.clone()],
    };
    let v = wait_submitted_and_running(&c, &s, &cl, &id);
    let jobs = recorded(&v);

    // SIGKILL: the SLURM jobs go on without the server.
    s.kill();
    let seen = tile_checkpoints(&s, &id);
    let start = Instant::now();
    while tile_checkpoints(&s, &id) <= seen {
        let st = named(&cl, &id);
        assert!(
            !st.iter().any(|t| t.1 == "CANCELLED"),
            "the kill cancelled tasks: {st:?}"
        );
        assert!(
            start.elapsed() < TIMEOUT,
            "no tile committed while the server was down: {st:?}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }

    // Started again on the same data directory: the job re-attaches to the same SLURM jobs
    // (none submitted again) and delivers the bytes of `qemd denoise`.
    let conf = cl.conf.clone();
    let s = Server::start(
        d.path(),
        &config(8_000),
        &[("SLURM_CONF", conf.to_str().unwrap())],
    );
    let done = wait(&c, &s, &id);
    assert_eq!(done["status"], "successful", "{done}\nlog:\n{}", s.log());
    assert_eq!(done["executor"], "slurm");
    assert_eq!(recorded(&done), jobs, "{done}");
    assert_eq!(done["slurm"]["resubmits"], 0, "{done}");
    assert!(s.log().contains("re-attaching"), "log:\n{}", s.log());
    let submitted: Vec<String> = named(&cl, &id)
        .iter()
        .map(|t| t.0.split('_').next().unwrap().to_string())
        .collect();
    assert!(
        submitted.iter().all(|a| jobs.iter().any(|j| &j.1 == a)),
        "jobs submitted after the restart: {submitted:?} vs {jobs:?}"
    );
    let bytes = download(&c, &s, &id);
    let want = cli(&d.path().join("in.ply"), &d.path().join("cli.ply"), &[]);
    assert!(
        bytes == want,
        "the re-attached job's bytes differ from qemd denoise"
    );
}
