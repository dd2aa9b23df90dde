//! The container files are correct by construction: every path `docker/Dockerfile` and
//! `docker/compose.yaml` reference exists in the repository, and every configuration key they set
//! (`QEMD_*` variables, `docker/qemd.toml`) is one the binary knows (`config::KEYS`). No Docker
//! engine is needed.

use std::path::{Path, PathBuf};

use qem_denoise::config::{Config, KEYS};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `QEMD_FOO` names the key `foo`, which must be known.
fn assert_known_env(var: &str, place: &str) {
    if let Some(key) = var.strip_prefix("QEMD_") {
        let key = key.to_ascii_lowercase();
        assert!(
            KEYS.contains(&key.as_str()),
            "{place}: {var} is not a configuration key"
        );
    }
}

/// The Dockerfile's instructions, continuation lines joined, comments dropped.
fn instructions(text: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut current = String::new();
    for line in text.lines() {
        let t = line.trim();
        if t.starts_with('#') || (t.is_empty() && current.is_empty()) {
            continue;
        }
        match t.strip_suffix('\\') {
            Some(head) => {
                current.push_str(head);
                current.push(' ');
            }
            None => {
                current.push_str(t);
                let (op, args) = current
                    .trim()
                    .split_once(' ')
                    .unwrap_or((current.trim(), ""));
                out.push((op.to_ascii_uppercase(), args.trim().to_string()));
                current.clear();
            }
        }
    }
    out
}

#[test]
fn dockerfile_paths_and_keys() {
    let text = std::fs::read_to_string(repo().join("docker/Dockerfile")).unwrap();
    let ins = instructions(&text);
    let froms = ins.iter().filter(|(op, _)| op == "FROM").count();
    assert!(froms >= 2, "multi-stage build expected");
    let mut copied_to = Vec::new();
    for (op, args) in &ins {
        match op.as_str() {
            "COPY" | "ADD" => {
                let words: Vec<&str> = args.split_whitespace().collect();
                let from_stage = words.iter().any(|w| w.starts_with("--from"));
                let paths: Vec<&str> = words
                    .iter()
                    .copied()
                    .filter(|w| !w.starts_with("--"))
                    .collect();
                let (dest, sources) = paths.split_last().expect("COPY has a destination");
                copied_to.push(dest.to_string());
                if !from_stage {
                    for s in sources {
                        assert!(
                            repo().join(s).exists(),
                            "Dockerfile copies {s}, which is not in the repository"
                        );
                    }
                }
            }
            "ENV" => {
                for pair in args.split_whitespace() {
                    let var = pair.split('=').next().unwrap();
                    assert_known_env(var, "Dockerfile");
                }
            }
            _ => {}
        }
    }
    // The non-root user, the health check and the config file the command names.
    let user = ins
        .iter()
        .rev()
        .find(|(op, _)| op == "USER")
        .map(|(_, a)| a.as_str());
    assert!(
        user.is_some_and(|u| u != "root" && u != "0"),
        "runs as {user:?}"
    );
    let health = ins
        .iter()
        .find(|(op, _)| op == "HEALTHCHECK")
        .map(|(_, a)| a.clone());
    assert!(health.is_some_and(|h| h.contains("/healthz")));
    let cmd = &ins.iter().rev().find(|(op, _)| op == "CMD").unwrap().1;
    for word in cmd
        .split(['"', ',', '[', ']', ' '])
        .filter(|w| w.starts_with('/'))
    {
        assert!(
            copied_to.iter().any(|d| d == word),
            "CMD names {word}, which no COPY provides"
        );
    }
}

#[test]
fn compose_paths_and_keys() {
    let dir = repo().join("docker");
    let text = std::fs::read_to_string(dir.join("compose.yaml")).unwrap();
    let doc: serde_json::Value = serde_norway::from_str(&text).unwrap();
    let services = doc["services"].as_object().expect("services");
    assert!(!services.is_empty());
    let rel = |p: &str| -> PathBuf { dir.join(p) };
    for (name, svc) in services {
        if let Some(build) = svc.get("build") {
            let context = rel(build["context"].as_str().unwrap_or("."));
            assert!(context.is_dir(), "{name}: build context missing");
            if let Some(df) = build["dockerfile"].as_str() {
                assert!(context.join(df).is_file(), "{name}: {df} missing");
            }
        }
        match svc.get("environment") {
            Some(serde_json::Value::Object(env)) => {
                for var in env.keys() {
                    assert_known_env(var, "compose.yaml");
                }
            }
            Some(serde_json::Value::Array(env)) => {
                for pair in env {
                    let var = pair.as_str().unwrap().split('=').next().unwrap();
                    assert_known_env(var, "compose.yaml");
                }
            }
            _ => {}
        }
        for v in svc["volumes"].as_array().into_iter().flatten() {
            let source = v.as_str().unwrap_or_default().split(':').next().unwrap();
            if source.starts_with('.') || source.starts_with('/') {
                assert!(
                    rel(source).exists(),
                    "{name}: volume source {source} missing"
                );
            }
        }
    }
    for (name, cfg) in doc["configs"].as_object().into_iter().flatten() {
        let file = cfg["file"].as_str().unwrap();
        let path = rel(file);
        assert!(path.is_file(), "config {name}: {file} missing");
        check_config_file(&path);
    }
}

/// Every key of a TOML file is known: loading it through the binary's own loader fails on an
/// unknown key or a bad value.
fn check_config_file(path: &Path) {
    let c = Config::load(Some(path)).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(
        c.listen.starts_with("0.0.0.0:"),
        "a container must listen on all interfaces"
    );
}

#[test]
fn container_config_file_is_valid() {
    check_config_file(&repo().join("docker/qemd.toml"));
}
