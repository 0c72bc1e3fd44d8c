"""The Python package against generated truth and against `dsq fit` on the same files.

Run from the repository: `pytest python/tests`. The `dsq` binary to compare with is $DSQ, or
target/release/dsq (`cargo build --release --no-default-features --bin dsq`).
"""

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import deformable_sq as d

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "assets" / "data"
DSQ = Path(os.environ.get("DSQ", REPO / "target" / "release" / "dsq"))


def superquadric_cloud(a, e1, e2, n, noise, seed):
    """Points on a superquadric with semi-axes `a` (along x, y, z), turned and moved."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-np.pi / 2, np.pi / 2, n)
    v = rng.uniform(-np.pi, np.pi, n)
    f = lambda x, e: np.sign(x) * np.abs(x) ** e  # noqa: E731
    p = np.stack(
        [
            a[0] * f(np.cos(u), e1) * f(np.cos(v), e2),
            a[1] * f(np.cos(u), e1) * f(np.sin(v), e2),
            a[2] * f(np.sin(u), e1),
        ],
        axis=1,
    )
    c, s = np.cos(0.6), np.sin(0.6)
    turn = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return p @ turn.T + np.array([1.0, -2.0, 0.5]) + rng.normal(scale=noise, size=p.shape)


def write_ply(path, pts):
    """`pts` as an ASCII PLY of double x, y, z vertices."""
    lines = "\n".join(" ".join(f"{x:.17g}" for x in p) for p in pts)
    path.write_text(
        f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty double x\n"
        f"property double y\nproperty double z\nend_header\n{lines}\n"
    )
    return path


def dsq(*args):
    assert DSQ.exists(), f"{DSQ} not built: cargo build --release --no-default-features --bin dsq"
    return subprocess.run([str(DSQ), "fit", *map(str, args)], capture_output=True, text=True)


def test_numpy_in_parameters_and_arrays_out_recover_a_generated_superquadric():
    pts = superquadric_cloud((0.5, 0.8, 1.4), 0.5, 1.0, 2000, 0.002, 1)
    r = d.fit(pts.astype(np.float32), global_only=True)
    assert r.converged and r.solver == "solved"
    semi = sorted(r.a * np.array(r.aspect))
    assert np.allclose(semi, [0.5, 0.8, 1.4], rtol=0.03), semi
    assert r.residuals["mean"] < 0.005
    assert np.allclose(r.translation, [1.0, -2.0, 0.5], atol=0.02)
    m = r.rotation_matrix
    assert m.shape == (3, 3) and np.allclose(m @ m.T, np.eye(3), atol=1e-9)
    w, x, y, z = r.rotation
    assert abs(w * w + x * x + y * y + z * z - 1) < 1e-9
    v, f = r.mesh()
    assert v.shape == (r.nodes, 3) and v.dtype == np.float64
    assert f.dtype == np.int64 and f.shape[1] == 3 and f.min() == 0 and f.max() == r.nodes - 1
    s = r.surface_points(500, seed=3)
    assert s.shape == (500, 3) and np.isfinite(s).all()
    # The samples lie on the mesh's triangles: each within its longest edge of a vertex.
    edges = np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2)
    nearest = np.min(np.linalg.norm(s[:, None, :] - v[None, :, :], axis=2), axis=1)
    assert nearest.max() <= edges.max()
    assert np.array_equal(s, r.surface_points(500, seed=3))


def test_the_same_file_fits_as_dsq_fit_bit_for_bit(tmp_path):
    rng = np.random.default_rng(5)
    noisy = superquadric_cloud((0.6, 0.9, 1.4), 0.5, 1.3, 500, 0.01, 21)
    noisy = np.vstack([noisy, rng.uniform(noisy.min(0), noisy.max(0), size=(100, 3))])
    partial = superquadric_cloud((0.5, 0.8, 1.1), 1.4, 0.7, 400, 0.0, 22)
    partial = partial[partial[:, 0] > np.median(partial[:, 0])]
    for path, flags in [
        (write_ply(tmp_path / "noisy.ply", noisy), []),
        (write_ply(tmp_path / "partial.ply", partial), ["--global-only"]),
        (DATA / "bunny_scan.obj", ["--global-only", "--taper", "--bend"]),
    ]:
        name = path.name
        out = tmp_path / "params.json"
        run = dsq(path, "--quiet", "--out-params", out, *flags)
        assert run.returncode == 0, run.stderr
        options = {f.lstrip("-").replace("-", "_"): True for f in flags}
        ours = d.fit(d.load_points(path), **options).to_dict()
        assert ours == json.loads(out.read_text()), name


def test_bad_input_raises_value_error_with_dsqs_message(tmp_path):
    few = np.random.default_rng(0).normal(size=(5, 3))
    ply = tmp_path / "few.ply"
    ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n" + "\n".join(" ".join(f"{x:.17g}" for x in p) for p in few)
    )
    cli = dsq(ply, "--quiet")
    assert cli.returncode == 2
    with pytest.raises(ValueError) as e:
        d.fit(few)
    assert cli.stderr.strip() == f"error: {ply}: {e.value}"
    nan = np.ones((100, 3))
    nan[7, 1] = np.nan
    for points, says in [
        (nan, "point 7 has a NaN"),
        (np.ones((100, 2)), "(N, 3)"),
        (np.ones(30), "(N, 3)"),
        ([["a", "b", "c"]] * 20, "cannot read"),
        (np.ones((100, 3)), "coincide"),
    ]:
        with pytest.raises(ValueError, match=None) as e:
            d.fit(points)
        assert says in str(e.value), (says, str(e.value))
    pts = superquadric_cloud((1, 1, 1), 1, 1, 200, 0.0, 2)
    for options, says in [
        ({"no_such_option": 1}, "unknown option"),
        ({"global_only": "yes"}, "global_only: expected True or False"),
        ({"solver": "newton"}, "not a solver"),
        ({"outliers": 1.5}, "outliers = 1.5 is out of range [0, 1)"),
        ({"nodes": 964}, "nearest is 963"),
        ({"w1": "often"}, "w1: expected a number"),
    ]:
        with pytest.raises(ValueError) as e:
            d.fit(pts, **options)
        assert says in str(e.value), (options, str(e.value))
    with pytest.raises(ValueError, match="broken.ply"):
        (tmp_path / "broken.ply").write_text("not a ply\n")
        d.load_points(tmp_path / "broken.ply")


def test_a_mesh_is_read_as_its_surface(tmp_path):
    obj = tmp_path / "tri.obj"
    obj.write_text("v 0 0 0\nv 2 0 0\nv 0 2 0\nf 1 2 3\n")
    pts = d.load_points(obj, mesh_samples=500)
    assert pts.shape == (500, 3)
    assert np.all(pts[:, 2] == 0) and np.all(pts[:, 0] + pts[:, 1] <= 2 + 1e-12)
    # Uniform by area: a quarter of the triangle holds a quarter of the points.
    assert abs(np.sum(pts[:, 0] + pts[:, 1] < 1) - 125) < 10
    assert d.load_points(obj).shape == (10000, 3)
    with pytest.raises(ValueError, match="mesh samples = 0 is out of range"):
        d.load_points(obj, mesh_samples=0)


def test_a_fit_releases_the_gil():
    pts = superquadric_cloud((0.5, 0.8, 1.4), 0.5, 1.0, 20000, 0.002, 4)
    done = threading.Event()
    ticks = 0

    def fit():
        d.fit(pts)
        done.set()

    t = threading.Thread(target=fit)
    t.start()
    # While the fit runs, this thread keeps running Python code only if the fit let go of the
    # GIL; holding it, the loop would get the GIL back only when the fit ends.
    while not done.is_set():
        ticks += 1
        time.sleep(0)
    t.join()
    assert ticks > 1000, ticks


def test_an_image_part_is_fitted_to_a_generated_disc():
    h, w = 120, 160
    rows, cols = np.mgrid[0:h, 0:w]
    image = np.where((cols - 80.0) ** 2 / 30**2 + (rows - 60.0) ** 2 / 20**2 <= 1, 40, 230)
    parts = d.fit_image(image.astype(np.uint8), [(58, 61, 102, 61, 80, 47, 80, 75)],
                        global_only=True)
    assert len(parts) == 1 and parts[0].converged and parts[0].stopped is None
    before, after = parts[0].outline
    assert after > before and after > 0.8
    v, f = parts[0].mesh()
    # The silhouette's extent in pixels (the image's longer side spans [-0.5, 0.5]).
    x = v[:, 0] * w + w / 2
    assert abs((x.max() - x.min()) - 60) < 4
    with pytest.raises(ValueError, match="parts\\[0\\]"):
        d.fit_image(image, [(1, 2, 3)])
    with pytest.raises(ValueError, match="unknown option"):
        d.fit_image(image, [(58, 61, 102, 61, 80, 47, 80, 75)], solvr="solved")
    with pytest.raises(ValueError, match="region sets the paper's dynamics"):
        d.fit_image(image, [(58, 61, 102, 61, 80, 47, 80, 75)], region=0.04)
    paper = d.fit_image(image, [(58, 61, 102, 61, 80, 47, 80, 75)], global_only=True,
                        region=0.04, solver="dynamics")
    assert paper[0].converged and paper[0].stopped is None


def test_the_dask_example_gives_the_cli_batchs_table(tmp_path):
    for i in range(6):
        pts = superquadric_cloud((0.4 + 0.1 * i, 0.8, 1.2), 0.3 + 0.2 * i, 1.0, 800, 0.005, 10 + i)
        write_ply(tmp_path / f"c{i}.ply", pts)
    table = tmp_path / "table.jsonl"
    example = REPO / "examples" / "python" / "batch_dask.py"
    run = subprocess.run(
        [sys.executable, str(example), str(tmp_path), "--workers", "2", "--global-only",
         "--out", str(table)],
        capture_output=True, text=True, timeout=600,
    )
    assert run.returncode == 0, run.stderr
    rows = [json.loads(line) for line in table.read_text().splitlines()]
    files = sorted(tmp_path.glob("c*.ply"))
    cli = dsq(*files, "--global-only", "--quiet")
    assert cli.returncode == 0, cli.stderr
    batch = [json.loads(line) for line in cli.stdout.splitlines()]
    assert [r["file"] for r in rows] == [b["file"] for b in batch] == list(map(str, files))
    for row, line in zip(rows, batch):
        for key in ("a", "a1", "a2", "a3", "e1", "e2", "mean", "p95", "converged", "steps"):
            assert row[key] == line[key], (row["file"], key)


# Every keyword over its whole space: at its bounds, past them, at 0, negative, huge, NaN,
# infinite and of the wrong type. A fit gives finite numbers or raises ValueError naming the
# keyword; never a panic (PanicException is not an Exception) or an abort.
EVERYWHERE = [0, -1, 1e300, 10**30, float("nan"), float("inf"), float("-inf"), "abc", None, [1], True]
FIT_VALUES = {
    "k": [3, 2, 836, 837], "nodes": [11, 6, 963, 964], "w0": [1e-300], "w1": ["auto", 1e-300],
    "beta": [1e-300], "max_steps": [1, 2**32 - 1, 2**32], "outliers": [0.999999, 1.0],
    "reassign": [1, 2**32 - 1], "implicit_local": [1e-300], "solver": ["solved", "dynamics", "x"],
    "global_only": [False], "taper": [False], "bend": [False], "robust": [False],
}
IMAGE_VALUES = {
    "sigma": [0.25, 0.2, 1e-300], "band": [1e-300], "region": [1e300], "k": [3, 837],
    "nodes": [11, 964], "w0": [1e300], "w1": [1e300], "beta": [1e-300, 1e300],
    "max_steps": [1, 2**64], "global_only": [False], "fix_epsilon": [False],
    "solver": ["dynamics", "solved", "paper"],
}


def finite(x):
    if isinstance(x, dict):
        return all(finite(v) for v in x.values())
    if isinstance(x, (list, tuple)):
        return all(finite(v) for v in x)
    if isinstance(x, float):
        return np.isfinite(x)
    return True


@pytest.mark.parametrize("key", sorted(FIT_VALUES))
def test_every_fit_keyword_fits_finitely_or_raises_value_error(key):
    pts = superquadric_cloud((0.5, 0.8, 1.1), 0.7, 1.2, 300, 0.005, 31)
    for v in FIT_VALUES[key] + EVERYWHERE:
        options = {key: v}
        if key != "max_steps":
            options["max_steps"] = 30
        if key in ("k", "nodes"):
            options["global_only"] = True
        try:
            r = d.fit(pts, **options)
        except ValueError as e:
            assert "\n" not in str(e) and key in str(e), (key, v, str(e))
            continue
        assert finite(r.to_dict()), (key, v, r.to_dict())


@pytest.mark.parametrize("key", sorted(IMAGE_VALUES))
def test_every_image_keyword_fits_finitely_or_raises_value_error(key):
    rows, cols = np.mgrid[0:120, 0:160]
    image = np.where((cols - 80.0) ** 2 / 30**2 + (rows - 60.0) ** 2 / 20**2 <= 1, 40, 230)
    image = image.astype(np.uint8)
    for v in IMAGE_VALUES[key] + EVERYWHERE:
        options = {key: v}
        if key != "solver":
            # The dynamics' options act with solver="dynamics" (the solved fit refuses them).
            options["solver"] = "dynamics"
        if key not in ("max_steps", "solver"):
            options["max_steps"] = 20
        try:
            parts = d.fit_image(image, [(58, 61, 102, 61, 80, 47, 80, 75)], **options)
        except ValueError as e:
            assert "\n" not in str(e) and key in str(e), (key, v, str(e))
            continue
        for p in parts:
            assert np.isfinite(p.translation).all() and np.isfinite(p.epsilon).all(), (key, v)


def test_fit_parts_splits_two_separate_superquadrics_as_dsq_does(tmp_path):
    a = superquadric_cloud((0.5, 0.5, 1.0), 0.5, 1.0, 600, 0.0, 31)
    b = superquadric_cloud((0.6, 0.4, 0.4), 1.0, 0.4, 600, 0.0, 32) + np.array([3.0, 0.0, 0.0])
    points = np.vstack([a, b])
    whole = d.fit_parts(points)
    assert len(whole) == 2
    owner = whole.owner
    assert owner.shape == (1200,)
    assert len(set(owner[:600])) == 1 and len(set(owner[600:])) == 1
    assert owner[0] != owner[600]
    for part in whole.parts:
        assert part.residuals["mean"] < 0.01 * 4.0
    # Two clean superquadrics: every point explained, by each part and by the whole.
    assert whole.explained == 1.0 and whole.part_explained == [1.0, 1.0]
    path = write_ply(tmp_path / "two.ply", points)
    out = tmp_path / "params.json"
    run = dsq(path, "--quiet", "--parts", "auto", "--out-params", out)
    assert run.returncode == 0, run.stderr
    assert [p.to_dict() for p in whole.parts] == json.loads(out.read_text())
    lines = [json.loads(line) for line in run.stdout.splitlines()]
    assert [line["explained"] for line in lines] == whole.part_explained + [whole.explained]
    with pytest.raises(ValueError, match="max_parts caps"):
        d.fit_parts(points, parts=2, max_parts=3)
    with pytest.raises(ValueError, match="parts = 0"):
        d.fit_parts(points, parts=0)


def sphere_video(frames, radius=0.06, step=0.004):
    """A sphere rolling along a floor, seen by Open3D's default camera (640×480, f = 525):
    depth in millimetres (uint16) per frame, and the true centres."""
    w, h, f, cx, cy = 640, 480, 525.0, 319.5, 239.5
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rx, ry = (u - cx) / f, (v - cy) / f
    floor_y = 0.25  # the floor y = 0.25 m (y down)
    out, centres = [], []
    for k in range(frames):
        c = np.array([-0.05 + step * k, floor_y - radius, 1.0])
        # |t r - c|² = radius², r = (rx, ry, 1): the nearest root.
        a = rx * rx + ry * ry + 1.0
        b = rx * c[0] + ry * c[1] + c[2]
        disc = b * b - a * (c @ c - radius * radius)
        t_sphere = np.where(disc > 0, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
        t_floor = np.where(ry > 1e-9, floor_y / np.maximum(ry, 1e-9), np.inf)
        t = np.minimum(t_sphere, t_floor)
        depth = np.where(np.isfinite(t) & (t < 5.0), np.round(t * 1000.0), 0).astype(np.uint16)
        out.append(depth)
        centres.append(c)
    return out, centres


def write_png16(path, depth):
    """`depth` (H×W uint16) as a 16-bit greyscale PNG, by zlib alone."""
    import struct
    import zlib

    h, w = depth.shape
    rows = b"".join(b"\x00" + depth[r].astype(">u2").tobytes() for r in range(h))

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows))
    path.write_bytes(png + chunk(b"IEND", b""))
    return path


def test_track_follows_a_rolling_sphere_as_dsq_track_does(tmp_path):
    frames, centres = sphere_video(8)
    roi = [255, 300, 335, 380]  # around the first frame's sphere (u 262–324, v 308–370)
    results = list(d.track(frames, roi=roi))
    assert len(results) == 8
    for r, c in zip(results, centres):
        assert not r["lost"]
        assert np.linalg.norm(np.array(r["translation"]) - c) < 0.003, (r["frame"], r["translation"], c)
        semi = r["a"] * np.array([r["a1"], r["a2"], r["a3"]])
        assert np.allclose(semi, 0.06, atol=0.004), semi

    # The same frames as PNG files through dsq track give the same lines, bit for bit.
    paths = [write_png16(tmp_path / f"depth_{k:03}.png", f) for k, f in enumerate(frames)]
    assert DSQ.exists(), f"{DSQ} not built: cargo build --release --no-default-features --bin dsq"
    run = subprocess.run(
        [str(DSQ), "track", "--quiet", "--roi", ",".join(map(str, roi)), *map(str, paths)],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    lines = [json.loads(l) for l in run.stdout.splitlines()]
    assert lines[-1]["frames"] == 8 and lines[-1]["lost"] == 0
    from_files = list(d.track(paths, roi=roi))
    for line, mine, arrays in zip(lines, from_files, results):
        del line["ms"]
        assert line == mine
        del mine["file"]
        assert mine == arrays

    # Started from a frame's dict, it goes on from there.
    later = list(d.track(frames[1:], init=results[0]))
    assert np.linalg.norm(np.array(later[-1]["translation"]) - centres[-1]) < 0.003


def test_track_names_bad_input(tmp_path):
    frames, _ = sphere_video(1)
    with pytest.raises(ValueError, match="give init"):
        next(d.track(frames))
    with pytest.raises(ValueError, match="depth_scale"):
        d.track(frames, roi=[0, 0, 10, 10], depth_scale=0.0)
    with pytest.raises(ValueError, match="outside the 640×480 image"):
        next(d.track(frames, roi=[600, 400, 700, 500]))
    with pytest.raises(ValueError, match=r"frames\[0\]: an array of shape \[10, 10\]"):
        next(d.track([np.zeros((10, 10), np.uint16)], roi=[0, 0, 5, 5]))
    with pytest.raises(ValueError, match="the first frame has no depth"):
        next(d.track([np.zeros((480, 640), np.uint16)], roi=[0, 0, 5, 5]))
    with pytest.raises(ValueError, match=r"frames\[0\]: .*missing.png: cannot read"):
        next(d.track([tmp_path / "missing.png"], roi=[0, 0, 5, 5]))
    with pytest.raises(ValueError, match="init: no `translation`"):
        next(d.track(frames, init={"a": 1}))
    with pytest.raises(ValueError, match="intrinsics: `intrinsic_matrix`"):
        next(d.track(frames, {"width": 640, "height": 480}, roi=[0, 0, 5, 5]))
