"""The qemd Python package: the array and file APIs against the CLI, bad input, threads, interop.

The CLI comparisons run the `qemd` binary named by $QEMD_BIN (CI builds target/release/qemd and
sets it); without it they are skipped with that reason.
"""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import qemd

ROOT = Path(__file__).resolve().parents[2]


def qemd_bin():
    path = os.environ.get("QEMD_BIN")
    if not path:
        pytest.skip("QEMD_BIN is not set: the CLI comparisons need the qemd binary")
    path = Path(path)
    if not path.is_absolute():
        path = (ROOT / path).resolve()
    if not path.exists():
        pytest.fail(f"QEMD_BIN={path} does not exist")
    return path


def cli(*args):
    r = subprocess.run([str(qemd_bin()), *map(str, args)], capture_output=True, text=True)
    return r


# ---------------------------------------------------------------------------------------------
# Test data and a minimal binary PLY reader and writer (double x, y, z; optional triangles).


def noisy_sphere(n=4000, seed=1, noise=0.01, centre=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * (1.0 + noise * rng.normal(size=(n, 1))) + np.asarray(centre)


def noisy_grid_mesh(m=30, seed=2):
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(0, 1, m), np.linspace(0, 1, m), indexing="ij")
    z = 0.1 * np.sin(3 * xs) + 0.005 * rng.normal(size=xs.shape)
    v = np.column_stack([xs.ravel(), ys.ravel(), z.ravel()])
    f = []
    for i in range(m - 1):
        for j in range(m - 1):
            a, b, c, d = i * m + j, (i + 1) * m + j, (i + 1) * m + j + 1, i * m + j + 1
            f += [(a, b, c), (a, c, d)]
    return v, np.asarray(f, dtype=np.int32)


def write_ply(path, pts, faces=None):
    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {len(pts)}",
        "property double x",
        "property double y",
        "property double z",
    ]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        f.write(np.ascontiguousarray(pts, dtype="<f8").tobytes())
        if faces is not None:
            rec = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
            rec["n"] = 3
            rec["i"] = faces
            f.write(rec.tobytes())


def read_ply_xyz(path):
    """The x, y, z of a binary little-endian PLY whose vertices are three doubles (plus, when
    present, one trailing property, such as the `noise` flag, of the type its header says)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode().splitlines()
    assert "format binary_little_endian 1.0" in lines, lines
    n = next(int(l.split()[2]) for l in lines if l.startswith("element vertex"))
    props = []
    in_vertex = False
    for l in lines:
        if l.startswith("element"):
            in_vertex = l.startswith("element vertex")
        elif l.startswith("property") and in_vertex:
            _, t, name = l.split()
            props.append((name, {"double": "<f8", "float": "<f4", "uchar": "u1", "int": "<i4"}[t]))
    rec = np.frombuffer(data, dtype=np.dtype(props), count=n, offset=end)
    return np.column_stack([rec["x"], rec["y"], rec["z"]]), rec


@pytest.fixture(scope="module")
def sphere():
    return noisy_sphere()


# ---------------------------------------------------------------------------------------------
# The array API equals the CLI, bit for bit.


@pytest.mark.parametrize(
    "params,flags",
    [
        ({}, []),
        ({"knn": 8}, ["--knn", "8"]),
        ({"method": "bilateral"}, ["--method", "bilateral"]),
        ({"paper": True}, ["--paper"]),
        ({"guard": False, "mu": 0.25, "max_move": 0.005}, ["--no-guard", "--mu", "0.25", "--max-move", "0.005"]),
        # issue 47: a station's beams, given as a list or as the CLI's text.
        ({"sensor_origin": [0.5, -0.25, 4.0]}, ["--sensor-origin", "0.5,-0.25,4"]),
        ({"sensor_origin": "0.5,-0.25,4"}, ["--sensor-origin", "0.5,-0.25,4"]),
    ],
)
def test_array_equals_cli_bytes(tmp_path, sphere, params, flags):
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(src, sphere)
    r = cli("denoise", src, "-o", dst, "-q", *flags)
    assert r.returncode == 0, r.stderr
    want, _ = read_ply_xyz(dst)
    got = qemd.denoise(sphere, **params)
    assert got.dtype == np.float64 and got.shape == sphere.shape
    assert got.tobytes() == want.tobytes()
    assert not np.array_equal(got, sphere)


def test_georeferenced_cloud_equals_cli(tmp_path):
    # Large coordinates: the f64 origin rule is the file path's.
    pts = noisy_sphere(2000, seed=3, centre=(512_345.25, 5_401_234.5, 312.0))
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(src, pts)
    r = cli("denoise", src, "-o", dst, "-q")
    assert r.returncode == 0, r.stderr
    want, _ = read_ply_xyz(dst)
    assert qemd.denoise(pts).tobytes() == want.tobytes()


def test_mesh_equals_cli_bytes(tmp_path):
    v, f = noisy_grid_mesh()
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(src, v, f)
    r = cli("denoise", src, "-o", dst, "-q")
    assert r.returncode == 0, r.stderr
    want, _ = read_ply_xyz(dst)
    got = qemd.denoise(v, faces=f)
    assert got.tobytes() == want.tobytes()
    # The same vertices as a cloud run in point mode, and differently.
    assert not np.array_equal(qemd.denoise(v), got)
    # Any integer dtype of faces.
    assert qemd.denoise(v, faces=f.astype(np.int64)).tobytes() == got.tobytes()
    assert qemd.denoise(v, faces=f.astype(np.uint32)).tobytes() == got.tobytes()
    # knn forces point mode, as on the command line.
    assert qemd.denoise(v, faces=f, knn=16).tobytes() == qemd.denoise(v, knn=16).tobytes()


def test_outliers_remove_equals_cli(tmp_path, sphere):
    pts = np.vstack([sphere, [[3.0, 3.0, 3.0], [-4.0, 2.0, 0.0]]])
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(src, pts)
    r = cli("denoise", src, "-o", dst, "-q", "--outliers", "remove")
    assert r.returncode == 0, r.stderr
    want, _ = read_ply_xyz(dst)
    got = qemd.denoise(pts, outliers="remove")
    assert len(got) < len(pts)
    assert got.tobytes() == want.tobytes()


def test_outliers_classify_equals_cli(tmp_path, sphere):
    pts = np.vstack([sphere, [[3.0, 3.0, 3.0]]])
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(src, pts)
    r = cli("denoise", src, "-o", dst, "-q", "--outliers", "classify")
    assert r.returncode == 0, r.stderr
    want, rec = read_ply_xyz(dst)
    got, noise = qemd.denoise(pts, outliers="classify")
    assert noise.dtype == np.bool_ and noise.shape == (len(pts),)
    assert noise[-1] and got[-1].tobytes() == pts[-1].tobytes()
    assert got.tobytes() == want.tobytes()
    assert np.array_equal(noise, rec["noise"] != 0)


# ---------------------------------------------------------------------------------------------
# The array and file APIs agree.


def test_file_api_equals_array_api(tmp_path, sphere):
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(src, sphere)
    report = qemd.denoise_file(src, dst, knn=12)
    assert isinstance(report, dict)
    assert report["mode"] == "points"
    assert report["points_in"] == report["points_out"] == len(sphere)
    assert report["params"]["knn"] == 12
    got, _ = read_ply_xyz(dst)
    assert got.tobytes() == qemd.denoise(sphere, knn=12).tobytes()


def test_file_api_tiled_out_of_core_is_the_same(tmp_path, sphere):
    src, a, b = tmp_path / "in.ply", tmp_path / "a.ply", tmp_path / "b.ply"
    write_ply(src, sphere)
    ra = qemd.denoise_file(src, a)
    rb = qemd.denoise_file(str(src), str(b), tile_points=1000, temp_dir=str(tmp_path))
    assert ra["mode"] == "points" and rb["mode"] == "tiled" and rb["tiles"] > 1
    assert a.read_bytes() == b.read_bytes()
    # The memory budget reaches the run: 1 MiB cannot hold this cloud's halo, as the CLI says.
    raises(qemd.denoise_file, src, tmp_path / "c.ply", memory_budget=1 << 20, match="memory budget")
    assert not (tmp_path / "c.ply").exists()


def test_file_api_formats(tmp_path, sphere):
    src, dst = tmp_path / "in.ply", tmp_path / "out.txt"
    write_ply(src, sphere)
    qemd.denoise_file(src, dst, output_format="xyz")
    back = np.loadtxt(dst)
    assert back.shape == sphere.shape
    assert np.allclose(back, qemd.denoise(sphere), atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Dtypes, layouts, threads, the GIL.


def test_float32_and_fortran_order(sphere):
    want = qemd.denoise(sphere)
    assert qemd.denoise(np.asfortranarray(sphere)).tobytes() == want.tobytes()
    strided = np.zeros((len(sphere), 6))
    strided[:, ::2] = sphere
    assert qemd.denoise(strided[:, ::2]).tobytes() == want.tobytes()
    p32 = sphere.astype(np.float32)
    got32 = qemd.denoise(p32)
    assert got32.dtype == np.float32
    # Computed in f64 from the widened values, rounded once at the end.
    assert got32.tobytes() == qemd.denoise(p32.astype(np.float64)).astype(np.float32).tobytes()
    assert qemd.denoise(np.asfortranarray(p32)).tobytes() == got32.tobytes()


def test_input_is_not_modified(sphere):
    before = sphere.copy()
    qemd.denoise(sphere)
    assert np.array_equal(before, sphere)


def test_threads_give_the_same_result(sphere):
    one = qemd.denoise(sphere, threads=1)
    two = qemd.denoise(sphere, threads=2)
    four = qemd.denoise(sphere, threads=4)
    assert one.tobytes() == two.tobytes() == four.tobytes() == qemd.denoise(sphere).tobytes()


def test_rayon_num_threads_gives_the_same_result(tmp_path, sphere):
    np.save(tmp_path / "p.npy", sphere)
    code = (
        "import sys, hashlib, numpy as np, qemd; "
        "p = np.load(sys.argv[1]); "
        "print(hashlib.sha256(qemd.denoise(p).tobytes()).hexdigest())"
    )
    digests = set()
    for n in ("1", "2", "3"):
        env = dict(os.environ, RAYON_NUM_THREADS=n)
        r = subprocess.run(
            [sys.executable, "-c", code, str(tmp_path / "p.npy")],
            capture_output=True, text=True, env=env,
        )
        assert r.returncode == 0, r.stderr
        digests.add(r.stdout.strip())
    assert len(digests) == 1


def test_gil_is_released_while_computing():
    pts = noisy_sphere(150_000, seed=5)
    ticks = 0
    done = threading.Event()

    def work():
        qemd.denoise(pts, threads=1)
        done.set()

    t = threading.Thread(target=work)
    start = time.perf_counter()
    t.start()
    while not done.is_set():
        ticks += 1
    t.join()
    elapsed = time.perf_counter() - start
    # This thread kept running pure-Python code while the other computed.
    assert elapsed > 0.05 and ticks > 10_000, (elapsed, ticks)


def test_ctrl_c_stops_a_run_with_keyboard_interrupt(tmp_path):
    # A process started with SIGINT ignored (a background job of a non-interactive shell, nohup)
    # passes that on, and Python then installs no handler: install it, so the test does not
    # depend on how the test run itself was started.
    code = (
        "import signal, sys, numpy as np, qemd\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "rng = np.random.default_rng(0)\n"
        "p = rng.random((1_000_000, 3))\n"
        "print('start', flush=True)\n"
        "try:\n"
        "    qemd.denoise(p)\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted', flush=True)\n"
        "    sys.exit(3)\n"
        "print('finished', flush=True)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "start"
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=300)
    assert proc.returncode == 3 and out.strip() == "interrupted", (proc.returncode, out)


# ---------------------------------------------------------------------------------------------
# Every bad input raises qemd.Error (a ValueError) with a one-line message.


def raises(fn, *args, match=None, **kwargs):
    with pytest.raises(qemd.Error) as e:
        fn(*args, **kwargs)
    msg = str(e.value)
    assert "\n" not in msg, msg
    if match is not None:
        assert match in msg, msg
    assert isinstance(e.value, ValueError)
    return msg


def test_bad_arrays_raise(sphere):
    bad_nan = sphere.copy()
    bad_nan[17, 1] = np.nan
    raises(qemd.denoise, bad_nan, match="row 17")
    bad_inf = sphere.copy()
    bad_inf[3, 0] = np.inf
    raises(qemd.denoise, bad_inf, match="row 3")
    far = sphere.copy()
    far[5, 2] = 1e13
    raises(qemd.denoise, far, match="row 5")
    raises(qemd.denoise, sphere[:, :2], match="shape (N, 3), got (4000, 2)")
    raises(qemd.denoise, sphere.ravel(), match="got (12000,)")
    raises(qemd.denoise, sphere[:, :, None], match="got (4000, 3, 1)")
    raises(qemd.denoise, np.zeros((0, 3)), match="no points")
    raises(qemd.denoise, sphere.astype(np.int64), match="float64 or float32")
    raises(qemd.denoise, sphere.astype(np.float16), match="float64 or float32")
    raises(qemd.denoise, sphere.tolist(), match="got list")
    raises(qemd.denoise, "points.ply", match="got str")
    raises(qemd.denoise, np.ones((40, 3)), match="all 40 points are identical")
    raises(qemd.denoise, sphere[:5], match="5")
    for fn in (qemd.normals, qemd.knn):
        args = (8,) if fn is qemd.knn else ()
        raises(fn, bad_nan, *args, match="row 17")
        raises(fn, sphere[:, :2], *args, match="shape")
        raises(fn, np.zeros((0, 3)), *args, match="no points")


def test_bad_faces_raise():
    v, f = noisy_grid_mesh(10)
    raises(qemd.denoise, v, faces=f[:, :2], match="faces: expected shape (M, 3)")
    raises(qemd.denoise, v, faces=f.astype(np.float64), match="faces: expected dtype")
    big = f.copy()
    big[4, 1] = len(v)
    raises(qemd.denoise, v, faces=big, match="faces: row 4 refers to vertex 100")
    neg = f.copy()
    neg[0, 0] = -1
    raises(qemd.denoise, v, faces=neg, match="refers to vertex -1")
    raises(qemd.denoise, v, faces=f, outliers="remove",
           match="invalid parameter outliers: applies to point clouds, not meshes")


def test_bad_parameters_raise_the_cli_messages(tmp_path, sphere):
    src = tmp_path / "in.ply"
    write_ply(src, sphere)
    cases = [
        ({"outlier_alpha": -1.0}, ["--outlier-alpha=-1"]),
        ({"knn": 2}, ["--knn", "2"]),
        ({"sigma_r": 5.0}, ["--sigma-r", "5"]),
        ({"eps": 1.5}, ["--eps", "1.5"]),
        ({"mu": -1.0}, ["--mu=-1"]),
        ({"rings": 0}, ["--rings", "0"]),
    ]
    for params, flags in cases:
        msg = raises(qemd.denoise, sphere, **params, match="invalid parameter")
        assert msg == raises(qemd.denoise_file, src, tmp_path / "o.ply", **params)
        r = cli("denoise", src, "-o", tmp_path / "o.ply", *flags)
        assert r.returncode != 0
        assert msg in r.stderr, (msg, r.stderr)
    assert not (tmp_path / "o.ply").exists()


def test_bad_keywords_raise(sphere):
    raises(qemd.denoise, sphere, knnn=3, match="unknown field `knnn`, expected one of")
    raises(qemd.denoise, sphere, knn=8.5, match="invalid parameter knn: invalid type")
    raises(qemd.denoise, sphere, knn=-1, match="invalid parameter knn: invalid value")
    raises(qemd.denoise, sphere, knn="8", match="invalid parameter knn")
    raises(qemd.denoise, sphere, method="fast", match="unknown variant `fast`")
    raises(qemd.denoise, sphere, mu=[1], match="invalid parameter mu")
    raises(qemd.denoise, sphere, **{"lambda": float("nan")}, match="invalid parameter lambda")
    raises(qemd.denoise, sphere, threads=0, match="threads")
    raises(qemd.denoise, sphere, memory_budget=1, match="unknown field `memory_budget`")
    raises(qemd.normals, sphere, knn=2, match="knn")
    raises(qemd.knn, sphere, 0, match="k")
    raises(qemd.knn, sphere[:4], 5, match="4")
    assert set(qemd.spec_fields()) >= {"knn", "method", "lambda", "outliers", "outlier_alpha"}
    raises(qemd.denoise, sphere, write_normals=True, match="write_normals: writes fields of an output file")


def test_issue9_denoise_file_writes_normals_as_the_cli(tmp_path, sphere):
    src = tmp_path / "in.ply"
    write_ply(src, sphere)
    report = qemd.denoise_file(src, tmp_path / "py.ply", write_normals=True)
    assert report["normals"] == "written"
    r = cli("denoise", src, "-o", tmp_path / "cli.ply", "--write-normals", "-q")
    assert r.returncode == 0, r.stderr
    py = (tmp_path / "py.ply").read_bytes()
    assert py == (tmp_path / "cli.ply").read_bytes()
    assert b"property float nx\nproperty float ny\nproperty float nz\n" in py[:400]


def test_file_errors_raise_naming_the_file(tmp_path, sphere):
    missing = tmp_path / "missing.ply"
    raises(qemd.denoise_file, missing, tmp_path / "o.ply", match=str(missing))
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"not a ply file at all")
    raises(qemd.denoise_file, garbage, tmp_path / "o.ply", match=str(garbage))
    src = tmp_path / "in.ply"
    write_ply(src, sphere)
    raises(qemd.denoise_file, src, src, match="refusing to overwrite the input file")
    raises(qemd.denoise_file, src, tmp_path / "o.ply", tile_points=0, match="tile_points")
    raises(qemd.denoise_file, src, tmp_path / "o.ply", output_format="docx", match="docx")
    raises(qemd.denoise_file, src, tmp_path / "o.ply", temp_dir=tmp_path / "nope", match="nope")
    assert not (tmp_path / "o.ply").exists()


# ---------------------------------------------------------------------------------------------
# normals and knn.


def test_knn_is_exact(sphere):
    pts = sphere[:500]
    idx, dist = qemd.knn(pts, 6)
    assert idx.shape == dist.shape == (500, 6)
    assert idx.dtype == np.int64 and dist.dtype == np.float64
    assert np.array_equal(idx[:, 0], np.arange(500)) and np.all(dist[:, 0] == 0)
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    brute = np.argsort(d, axis=1, kind="stable")[:, :6]
    assert np.array_equal(idx, brute)
    assert np.allclose(dist, np.take_along_axis(d, brute, axis=1), rtol=1e-12, atol=1e-15)
    assert np.all(np.diff(dist, axis=1) >= 0)


def test_normals_of_a_plane_and_a_sphere(sphere):
    rng = np.random.default_rng(7)
    plane = np.column_stack([rng.random(2000), rng.random(2000), np.zeros(2000)])
    n = qemd.normals(plane)
    assert n.shape == plane.shape
    assert np.allclose(np.abs(n[:, 2]), 1.0)
    clean = sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    ns = qemd.normals(clean, knn=10)
    assert np.allclose(np.linalg.norm(ns, axis=1), 1.0)
    assert np.min(np.abs(np.sum(ns * clean, axis=1))) > 0.99
    assert qemd.normals(clean.astype(np.float32), knn=10).dtype == np.float32
    assert qemd.normals(clean, 10, threads=1).tobytes() == ns.tobytes()


# ---------------------------------------------------------------------------------------------
# Interop: laspy, PyTorch, Open3D.


def test_laspy_lasdata_scaled_xyz(tmp_path):
    laspy = pytest.importorskip("laspy", reason="laspy is not installed (pip install 'laspy[lazrs]')")
    pts = noisy_sphere(3000, seed=11, noise=0.02) * 10 + [651_000.0, 4_720_000.0, 200.0]
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([651_000.0, 4_720_000.0, 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.intensity = np.arange(len(pts), dtype=np.uint16)
    src = tmp_path / "in.laz"
    las.write(src)

    # The array path: scaled x/y/z out of the LasData, the denoised values back into it.
    las = laspy.read(src)
    xyz = np.column_stack([las.x, las.y, las.z])
    out = qemd.denoise(xyz)
    las.x, las.y, las.z = out[:, 0], out[:, 1], out[:, 2]
    mine = tmp_path / "mine.laz"
    las.write(mine)

    # The file path on the same file keeps every other field and stores the same positions, with
    # one difference in rounding: laspy rounds each coordinate to the nearest 1 mm step, while a
    # denoising run never stores a move longer than the one it computed (points::store_move).
    # Where nearest would lengthen a point's move, its three coordinates round towards the
    # input's instead. Recompute that rule here from the array output and compare.
    report = qemd.denoise_file(src, tmp_path / "file.laz")
    assert report["points_out"] == len(pts)
    a, b = laspy.read(mine), laspy.read(tmp_path / "file.laz")
    assert np.array_equal(b.intensity, np.arange(len(pts)))
    ints = lambda d: np.column_stack([np.asarray(d[k], dtype=np.int64) for k in "XYZ"])
    start, near, got = ints(laspy.read(src)), ints(a), ints(b)
    units = (out - header.offsets) / header.scales
    toward = np.where(start < units, np.floor(units), np.where(start > units, np.ceil(units), near))
    longer = np.sum((near - start) ** 2, axis=1) > np.sum((units - start) ** 2, axis=1)
    expected = np.where(longer[:, None], toward, near).astype(np.int64)
    # Both sides may differ by one step where a value lies on a rounding boundary.
    assert np.abs(got - near).max() <= 1
    assert np.abs(got - expected).max() <= 1
    assert np.mean(np.all(got == expected, axis=1)) > 0.999
    # No stored move is longer than the computed one, and the rule did bite here.
    assert np.all(np.sum((got - start) ** 2, axis=1) <= np.sum((units - start) ** 2, axis=1) + 1e-6)
    assert longer.any() and not np.array_equal(got, near)
    assert not np.array_equal(near[:, 0], start[:, 0])


def test_pytorch_tensor_via_numpy(sphere):
    torch = pytest.importorskip(
        "torch", reason="PyTorch is not installed (too heavy for CI); the example needs it"
    )
    t = torch.from_numpy(sphere.astype(np.float32))
    out = torch.from_numpy(qemd.denoise(t.numpy()))
    assert out.dtype == torch.float32 and tuple(out.shape) == tuple(t.shape)
    assert np.array_equal(out.numpy(), qemd.denoise(sphere.astype(np.float32)))


def test_open3d_pointcloud(sphere):
    o3d = pytest.importorskip("open3d", reason="Open3D is not installed; the example needs it")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sphere))
    pcd.points = o3d.utility.Vector3dVector(qemd.denoise(np.asarray(pcd.points)))
    assert np.array_equal(np.asarray(pcd.points), qemd.denoise(sphere))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=16))
    assert np.asarray(pcd.normals).shape == sphere.shape
