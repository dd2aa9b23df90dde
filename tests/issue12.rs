//! Issue 12's smaller fixes, through the real binary: every default in `denoise --help`, the
//! default operator in `qemd table`, the σ line of `qemd noise`.

use std::process::Output;

use crate::util::{qemd, s};

fn ok(args: &[&str]) -> Output {
    let o = qemd(args);
    assert!(
        o.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

/// The long help of one option: its lines up to the next option.
fn option_help<'a>(help: &'a str, flag: &str) -> String {
    let is_option = |l: &str| {
        let indent = l.len() - l.trim_start().len();
        l.trim_start().starts_with('-') && indent <= 6
    };
    let mut lines = help
        .lines()
        .skip_while(|l| !(is_option(l) && l.trim_start().split([' ', ',']).any(|w| w == flag)));
    let first: &'a str = lines.next().unwrap_or_else(|| panic!("{flag} in the help"));
    let rest: Vec<&str> = lines
        // Option lines are indented by at most 6 spaces, their help text (and the lists of
        // possible values) by more.
        .take_while(|l| !is_option(l))
        .collect();
    format!("{first}\n{}", rest.join("\n"))
}

#[test]
fn issue12_denoise_help_states_every_default() {
    let o = ok(&["denoise", "--help"]);
    let help = String::from_utf8(o.stdout).unwrap();
    for flag in [
        "--method",
        "--planes",
        "--filter",
        "--updates",
        "--mu",
        "--sigma-r",
        "--max-move",
        "--rings",
        "--knn",
        "--normals",
        "--solve",
        "--eps",
        "--lambda",
        "--iterations",
        "--threads",
        "--outliers",
        "--outlier-alpha",
        "--memory-budget",
        "--temp-dir",
        "--tile-points",
        "--bin-fields",
    ] {
        let text = option_help(&help, flag).to_lowercase();
        assert!(
            text.contains("default"),
            "{flag} states no default:\n{text}"
        );
    }
    assert!(option_help(&help, "--iterations").contains("1 on clouds"));
    // The parameter spec's flags state the defaults in words (they are optional: unset, the
    // base — the default operator or --paper's — stays); spec.rs checks the words against
    // `Params::default()`.
    assert!(option_help(&help, "--normals").contains("default area"));
    assert!(option_help(&help, "--rings").contains("default 2"));
    assert!(option_help(&help, "--eps").contains("default 0.01"));
    assert!(option_help(&help, "--memory-budget").contains("1 GiB"));
    for flag in ["--format", "--input-format"] {
        let text = option_help(&help, flag);
        assert!(
            text.contains("[possible values: ply, obj, off, xyz, txt, pts, pcd, las, laz, copc, kitti, bin, nuscenes, e57]"),
            "{flag} lists its values:\n{text}"
        );
    }
    assert!(option_help(&help, "--format").contains("--output-format"));
}

#[test]
fn issue12_table_includes_the_default_operator() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("sphere.ply");
    ok(&["synth", "sphere", "-o", s(&mesh), "--resolution", "3"]);
    let o = ok(&["table", s(&mesh)]);
    let text = String::from_utf8(o.stdout).unwrap();
    for row in ["| qem |", "| bilateral |", "| default |"] {
        assert!(text.contains(row), "{row} in\n{text}");
    }
    let o = ok(&["table", s(&mesh), "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let names = j.to_string();
    assert!(names.contains("\"default\""), "{names}");
}

#[test]
fn issue12_noise_prints_level_times_l() {
    let dir = tempfile::tempdir().unwrap();
    let clean = dir.path().join("clean.ply");
    ok(&["synth", "cube", "-o", s(&clean), "--resolution", "6"]);
    let o = ok(&[
        "noise",
        s(&clean),
        "-o",
        s(&dir.path().join("noisy.ply")),
        "--level",
        "0.4",
    ]);
    let err = String::from_utf8(o.stderr).unwrap();
    // "… σ = 0.4 × L = <σ> (L = <L>)"
    let after = err
        .split("σ = 0.4 × L = ")
        .nth(1)
        .unwrap_or_else(|| panic!("{err}"));
    let sigma: f64 = after.split_whitespace().next().unwrap().parse().unwrap();
    let l: f64 = after
        .split("(L = ")
        .nth(1)
        .and_then(|r| r.split(')').next())
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        (sigma - 0.4 * l).abs() <= 1e-6 * l,
        "σ {sigma} vs 0.4 × L, L = {l}"
    );
}

#[test]
fn issue12_render_up_and_colour_flags() {
    use glam::DVec3;
    use qem_denoise::io::Cloud;
    use qem_denoise::points::ScalarType;
    let dir = tempfile::tempdir().unwrap();
    let pts: Vec<DVec3> = (0..900)
        .map(|i| DVec3::new((i % 30) as f64, (i / 30) as f64, 0.1 * (i % 7) as f64))
        .collect();
    let las = dir.path().join("ground.las");
    let ply = dir.path().join("ground.ply");
    let cloud = Cloud::generated(pts, None, ScalarType::F64);
    cloud.write(&las, None).unwrap();
    cloud.write(&ply, None).unwrap();
    for colour in ["height", "intensity", "class"] {
        let png = dir.path().join(format!("{colour}.png"));
        ok(&[
            "render",
            s(&las),
            "-o",
            s(&png),
            "--view",
            "top",
            "--colour",
            colour,
            "--size",
            "64x64",
        ]);
        assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
    }
    ok(&[
        "render",
        s(&ply),
        "-o",
        s(&dir.path().join("up.png")),
        "--up",
        "z",
        "--size",
        "64x64",
    ]);
    let out = dir.path().join("none.png");
    let o = qemd(&["render", s(&ply), "-o", s(&out), "--colour", "intensity"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(err.contains(s(&ply)) && err.contains("intensity"), "{err}");
    assert!(!out.exists());
}

#[test]
#[ignore = "needs ../shared"]
fn issue12_render_shared_las_by_class_from_the_top() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("top.png");
    ok(&[
        "render",
        "../shared/data/lidar/sample_c.las",
        "-o",
        s(&png),
        "--view",
        "top",
        "--colour",
        "class",
        "--size",
        "200x200",
    ]);
    assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
}

/// A noisy sphere mesh: positions and triangles (0-based).
fn noisy_sphere() -> (Vec<glam::DVec3>, Vec<[u32; 3]>) {
    use qem_denoise::eval::synth::Shape;
    let m = Shape::Sphere.mesh(3).unwrap();
    let pos: Vec<glam::DVec3> = m
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| *p * (1.0 + 0.01 * ((i * 7919 % 13) as f64 / 13.0 - 0.5)))
        .collect();
    let faces = m.faces.iter().map(|f| [f[0], f[1], f[2]]).collect();
    (pos, faces)
}

/// The area-weighted vertex normals of a mesh.
fn fresh(pos: &[glam::DVec3], faces: &[[u32; 3]]) -> Vec<glam::DVec3> {
    use qem_denoise::denoise::NormalWeighting;
    use qem_denoise::denoise::normals::vertex_normals;
    use qem_denoise::points::Faces;
    let mut f = Faces::new();
    for t in faces {
        f.push(t);
    }
    vertex_normals(pos, &f, NormalWeighting::Area).normals
}

/// Asserts `normals` are the area-weighted vertex normals of the mesh, pointing outwards.
fn assert_fresh_normals(pos: &[glam::DVec3], faces: &[[u32; 3]], normals: &[glam::DVec3]) {
    let want = fresh(pos, faces);
    assert_eq!(normals.len(), want.len());
    for (i, (n, w)) in normals.iter().zip(&want).enumerate() {
        assert!(n.angle_between(*w) < 1e-5, "vertex {i}: {n} vs {w}");
        assert!(n.dot(pos[i]) > 0.0, "outwards");
    }
}

#[test]
fn issue12_obj_vn_are_recomputed_not_stale() {
    let dir = tempfile::tempdir().unwrap();
    let (pos, faces) = noisy_sphere();
    // The input's own normals, which go stale when the vertices move; faces reference them as
    // v//vn.
    let stale = fresh(&pos, &faces);
    let mut obj = String::from("# sphere\n");
    for p in &pos {
        obj += &format!("v {} {} {}\n", p.x, p.y, p.z);
    }
    for n in &stale {
        obj += &format!("vn {} {} {}\n", n.x, n.y, n.z);
    }
    for t in &faces {
        obj += &format!(
            "f {a}//{a} {b}//{b} {c}//{c}\n",
            a = t[0] + 1,
            b = t[1] + 1,
            c = t[2] + 1
        );
    }
    let input = dir.path().join("in.obj");
    std::fs::write(&input, obj).unwrap();
    let out = dir.path().join("out.obj");
    let o = ok(&["denoise", s(&input), "-o", s(&out)]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("normals were recomputed"));
    let text = std::fs::read_to_string(&out).unwrap();
    let parse = |kw: &str| -> Vec<glam::DVec3> {
        text.lines()
            .filter(|l| l.starts_with(&format!("{kw} ")))
            .map(|l| {
                let v: Vec<f64> = l[kw.len() + 1..]
                    .split_whitespace()
                    .map(|t| t.parse().unwrap())
                    .collect();
                glam::DVec3::new(v[0], v[1], v[2])
            })
            .collect()
    };
    let (v, vn) = (parse("v"), parse("vn"));
    assert_ne!(v, pos, "the vertices moved");
    assert_fresh_normals(&v, &faces, &vn);
    assert!(
        vn.iter()
            .zip(&stale)
            .any(|(a, b)| a.angle_between(*b) > 1e-3),
        "the stale normals are gone"
    );
    // Everything else is kept: the comment and the face lines.
    assert!(text.starts_with("# sphere\n"));
    assert_eq!(
        text.lines().filter(|l| l.starts_with("f ")).count(),
        faces.len()
    );
}

#[test]
fn issue12_ply_normals_recomputed_on_meshes_cleared_on_clouds() {
    let dir = tempfile::tempdir().unwrap();
    let (pos, faces) = noisy_sphere();
    let mut ply = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty double x\nproperty double y\n\
         property double z\nproperty float nx\nproperty float ny\nproperty float nz\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        pos.len(),
        faces.len()
    );
    for (p, n) in pos.iter().zip(fresh(&pos, &faces)) {
        ply += &format!("{} {} {} {} {} {}\n", p.x, p.y, p.z, n.x, n.y, n.z);
    }
    for t in &faces {
        ply += &format!("3 {} {} {}\n", t[0], t[1], t[2]);
    }
    let input = dir.path().join("mesh.ply");
    std::fs::write(&input, &ply).unwrap();
    let out = dir.path().join("out.ply");
    ok(&["denoise", s(&input), "-o", s(&out)]);
    let c = qem_denoise::io::Cloud::read(&out, None).unwrap();
    let sch = &c.info.schema;
    let f = ["nx", "ny", "nz"].map(|n| sch.field_index(n).unwrap());
    let normals: Vec<glam::DVec3> = c
        .records
        .chunks_exact(sch.record_len)
        .map(|r| {
            glam::DVec3::new(
                sch.get_f64(r, f[0]),
                sch.get_f64(r, f[1]),
                sch.get_f64(r, f[2]),
            )
        })
        .collect();
    // Stored as float: compare in single precision.
    let pos_out = c.positions.clone();
    for (i, n) in normals.iter().enumerate() {
        assert!(
            n.dot(pos_out[i]) > 0.0 && (n.length() - 1.0).abs() < 1e-6,
            "{i}: {n}"
        );
    }
    let unit: Vec<glam::DVec3> = normals.iter().map(|n| n.normalize()).collect();
    assert_fresh_normals(&pos_out, &faces, &unit);

    // The same vertices as a point cloud (no faces): normals cleared, with a warning.
    let cloud_ply = ply.replace(
        &format!(
            "element face {}\nproperty list uchar int vertex_indices\n",
            faces.len()
        ),
        "",
    );
    let cloud_ply = cloud_ply
        .lines()
        .filter(|l| !l.starts_with("3 "))
        .collect::<Vec<_>>()
        .join("\n")
        + "\n";
    let input = dir.path().join("cloud.ply");
    std::fs::write(&input, cloud_ply).unwrap();
    for extra in [&[][..], &["--tile-points", "200"][..]] {
        let out = dir.path().join("cloud-out.ply");
        let mut args = vec!["denoise", s(&input), "-o", s(&out)];
        args.extend_from_slice(extra);
        let o = ok(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains("normals would be stale"), "{err}");
        let c = qem_denoise::io::Cloud::read(&out, None).unwrap();
        let sch = &c.info.schema;
        let nx = sch.field_index("nx").unwrap();
        assert!(
            c.records
                .chunks_exact(sch.record_len)
                .all(|r| sch.get_f64(r, nx).is_nan())
        );
    }
}
