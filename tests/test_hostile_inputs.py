"""Hostile input and faults (issue 17): each case through the CLI, one `error:` line naming the culprit,
the right exit code, and nothing written outside the output folder, no partial file left behind."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import pytest
from helpers import assert_one_line_error, invoke

from plotmosaic.align.outliers import stray_mask
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.config.align import AlignConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.cache import PairCache
from plotmosaic.io.atomic import remove_stale_temporaries
from plotmosaic.io.las import read_cloud
from plotmosaic.poses import load_poses

PLOTMOSAIC = [sys.executable, "-m", "plotmosaic"]


def tree(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def assert_nothing_left(root: Path, before: set[str], allowed: Path | None = None) -> None:
    """No new path under `root` except inside `allowed`, and no temporary file anywhere."""
    new = tree(root) - before
    if allowed is not None:
        new = {p for p in new if not (root / p).resolve().is_relative_to(allowed.resolve())}
    assert not new, f"left behind: {sorted(new)}"
    assert not [p for p in tree(root) if ".tmp-" in p], sorted(tree(root))


def with_stray(src: Path, dst: Path, how: str) -> Path:
    """A copy of a LAS/LAZ with one more point: 1 km away in x, or the X integer laspy writes for NaN."""
    las = laspy.read(src)
    extra = las.points[:1].copy()
    if how == "nan":
        extra.X = np.array([np.iinfo(np.int32).min], dtype=np.int32)
    else:
        extra.X = extra.X + np.int32(round(1000.0 / las.header.scales[0]))
    out = laspy.LasData(las.header)
    out.points = laspy.ScaleAwarePointRecord(
        np.concatenate([las.points.array, extra.array]),
        las.points.point_format,
        las.header.scales,
        las.header.offsets,
    )
    out.write(dst)
    return dst


def truth_pair(sim, source: str, target: str) -> np.ndarray:
    truth = load_poses(sim.ground_truth_path)
    return np.linalg.inv(truth.transform(target)) @ truth.transform(source)


def pose_error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    D = np.linalg.inv(T_true) @ T
    return float(np.linalg.norm(D[:3, 3])), float(
        np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    )


def write_manifest(path: Path, sim, scans: list[str], als: bool = True) -> Path:
    lines = ["version = 1"]
    if als:
        lines += ["[[als]]", f'path = "{sim.manifest_path.parent / "als" / "als.laz"}"']
    lines += ["[[plots]]", 'id = "P1"', 'crs = "EPSG:26912"']
    for sid in scans:
        lines += [
            "[[plots.scans]]",
            f'id = "{sid}"',
            f'path = "{sim.scan_paths[sid]}"',
            'kind = "tls"',
        ]
    path.write_text("\n".join(lines) + "\n")
    return path


# ---- item 2: stray points -------------------------------------------------------------------


def test_stray_mask_drops_only_detached_points():
    rng = np.random.default_rng(0)
    xyz = rng.normal(0, 20, (20_000, 3))
    xyz[:400] += [300.0, 0, 0]  # a real far part (2 %) beyond a gap: stays
    assert stray_mask(xyz).all()
    xyz[5] = [1e7, 0, 0]
    xyz[7] = [0, 0, -2_147_483.0]
    xyz[9] = [0, 800.0, 0]
    xyz[1000:1050] = [-2_147_483.0, 5.0, 3.0]  # fifty NaN-written points: one detached cluster
    assert sorted(np.flatnonzero(~stray_mask(xyz))) == [5, 7, 9, *range(1000, 1050)]


@pytest.mark.parametrize("how", ["nan", "1km"])
def test_stray_point_leaves_the_prepared_cloud_unchanged(small_sim, tmp_path, how):
    src = small_sim.scan_paths["P1-S1"]
    clean = prepare_cloud(read_cloud(src, attributes=False), "tls", 3, AlignConfig(), 0, "source")
    stray = prepare_cloud(
        read_cloud(with_stray(src, tmp_path / "s.laz", how), attributes=False),
        "tls",
        3,
        AlignConfig(),
        0,
        "source",
    )
    assert stray.stray_points == 1 and clean.stray_points == 0
    np.testing.assert_array_equal(stray.frame.offset, clean.frame.offset)
    np.testing.assert_array_equal(stray.points, clean.points)
    np.testing.assert_array_equal(stray.levels, clean.levels)


@pytest.mark.slow
def test_align_with_a_nan_written_stray_point_registers(small_sim, tmp_path):
    src = with_stray(small_sim.scan_paths["P1-S1"], tmp_path / "stray.laz", "nan")
    out = tmp_path / "out" / "r.json"
    res = invoke("align", src, small_sim.scan_paths["P1-S0"], "--out", out)
    assert res.exit_code == 0, res.output
    dt, dr = pose_error(
        np.asarray(json.loads(out.read_text())["transform"]),
        truth_pair(small_sim, "P1-S1", "P1-S0"),
    )
    assert dt < 0.05 and dr < 0.2, (dt, dr)


# ---- item 3: reflections ----------------------------------------------------------------------


def reflected(T) -> list:
    T = np.array(T, dtype=float)
    T[:3, 2] *= -1.0
    return T.tolist()


def test_merge_refuses_a_reflected_pose(small_sim, tmp_path):
    data = json.loads(small_sim.ground_truth_path.read_text())
    data["scans"]["P1-S2"]["transform"] = reflected(data["scans"]["P1-S2"]["transform"])
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps(data))
    before = tree(tmp_path)
    res = invoke(
        "merge", small_sim.manifest_path, "--poses", poses, "--out", tmp_path / "m" / "merged.laz"
    )
    assert_one_line_error(res, "poses.json", "P1-S2", "reflection")
    assert_nothing_left(tmp_path, before)


def test_align_refuses_a_reflected_init_before_work(small_sim, tmp_path):
    init = tmp_path / "init.json"
    init.write_text(json.dumps({"transform": reflected(np.eye(4))}))
    before = tree(tmp_path)
    res = invoke(
        "align",
        small_sim.scan_paths["P1-S1"],
        small_sim.scan_paths["P1-S0"],
        "--init",
        init,
        "--out",
        tmp_path / "RESULT.json",
    )
    assert_one_line_error(res, "init.json", "reflection")
    assert_nothing_left(tmp_path, before)


@pytest.mark.parametrize(
    "T, why", [(np.diag([1.0, 1.0, 1.001, 1.0]), "orthonormal"), (np.full((4, 4), np.nan), "NaN")]
)
def test_align_refuses_a_non_rigid_init(small_sim, tmp_path, T, why):
    init = tmp_path / "init.json"
    init.write_text(json.dumps({"transform": T.tolist()}))
    res = invoke(
        "align", small_sim.scan_paths["P1-S1"], small_sim.scan_paths["P1-S0"], "--init", init
    )
    assert_one_line_error(res, "init.json", why)


# ---- item 5: damaged cache entries (unit level; the CLI recovery is in the fault test below) ------


def test_damaged_cache_entries_are_discarded_with_one_warning(tmp_path, capsys):
    cache = PairCache(tmp_path / "pairs")
    good = {
        "source": "a",
        "target": "b",
        "key": "k1",
        "status": "ok",
        "transform": np.eye(4).tolist(),
        "information": np.eye(6).tolist(),
        "fitness": 0.5,
        "inlier_rmse": 0.02,
        "overlap": 0.4,
    }
    cache.put("k1", good)
    assert cache.get("k1")["transform"] == good["transform"]
    assert (
        "graph.json" in json.loads(cache.path("k1").read_text())["scope"]
    )  # the graph's verdict is not here
    nan = {**good, "key": "k3", "transform": [[float("nan")] * 4] * 4}
    damaged = {
        "k2": json.dumps({k: v for k, v in {**good, "key": "k2"}.items() if k != "transform"}),
        "k3": json.dumps(nan),  # json writes NaN
        "k4": "{ not json",
        "k5": json.dumps({**good, "key": "k5", "transform": reflected(np.eye(4))}),
    }
    for key, text in damaged.items():
        cache.path(key).write_text(text)
    capsys.readouterr()
    for key in damaged:
        assert cache.get(key) is None
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("warning: ") and f"{key}.json" in err[0], err


# ---- item 6: unwritable outputs, found before the work starts -------------------------------------


def test_unwritable_outputs_are_refused_before_work(small_sim, tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    src, tgt = small_sim.scan_paths["P1-S1"], small_sim.scan_paths["P1-S0"]

    def started(*args, **kwargs):
        raise AssertionError("the work started before the output location was checked")

    # patched where the commands look them up: a command module first imported under a patch of
    # the defining module would keep the stub for every later test of the process
    for where in (
        "plotmosaic.commands.align.align_files",
        "plotmosaic.commands.register.register_plot",
        "plotmosaic.commands.merge.merge_scans",
    ):
        monkeypatch.setattr(where, started)
    before = tree(tmp_path)
    assert_one_line_error(
        invoke("align", src, tgt, "--out", blocker / "r.json"), "a_file", "is a file"
    )
    assert_one_line_error(
        invoke("register-plot", small_sim.manifest_path, "--out", blocker / "reg"), "a_file"
    )
    assert_one_line_error(
        invoke("register-plot", small_sim.manifest_path, "--out", "/proc/plotmosaic-reg"), "/proc"
    )
    long = tmp_path / ("x" * 300 + ".laz")
    assert_one_line_error(
        invoke(
            "merge", small_sim.manifest_path, "--poses", small_sim.ground_truth_path, "--out", long
        ),
        "255",
    )
    assert_one_line_error(invoke("info", long), "too long")
    assert_nothing_left(tmp_path, before)
    assert not Path("/proc/plotmosaic-reg").exists()


# ---- item 7: interrupts and stale temporaries ---------------------------------------------------


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_stale_temporaries_are_removed_by_the_next_run(small_sim, tmp_path):
    out = tmp_path / "m" / "merged.laz"
    out.parent.mkdir()
    stale = out.parent / f".merged.laz.tmp-{dead_pid()}"
    stale.write_bytes(b"\0" * 1000)
    stale_dir = (
        out.parent / f".merged.laz.spill.tmp-{dead_pid()}"
    )  # a killed run's temporary folder
    (stale_dir / "tile").mkdir(parents=True)
    (stale_dir / "tile" / "0.bin").write_bytes(b"\0")
    live = out.parent / f".other.laz.tmp-{os.getpid()}"  # a live run's temporary is not touched
    live.write_bytes(b"\0")
    res = invoke(
        "merge", small_sim.manifest_path, "--poses", small_sim.ground_truth_path, "--out", out
    )
    assert res.exit_code == 0, res.output
    assert out.is_file() and not stale.exists() and not stale_dir.exists() and live.exists()
    assert remove_stale_temporaries(out.parent) == []  # once per folder and process


def test_an_interrupt_wrapped_by_a_library_exits_130():
    import typer
    from typer.testing import CliRunner

    from plotmosaic.commands.common import handle_errors

    @handle_errors
    def command() -> None:
        try:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C landing inside a codec callback ...
            time.sleep(1)
        except KeyboardInterrupt:
            raise RuntimeError(
                "Failed to call write"
            ) from None  # ... which reports it as its own error

    app = typer.Typer()
    app.command()(command)
    res = CliRunner().invoke(app, [])
    assert res.exit_code == 130, res.output
    assert res.output.strip() == "interrupted"


# ---- item 8: smaller ones -------------------------------------------------------------------------


def test_tie_to_als_with_poses_of_another_manifest(small_sim, tmp_path):
    data = json.loads(small_sim.ground_truth_path.read_text())
    data["frame"] = "plot"
    data["scans"] = {f"Q{k}": v for k, v in data["scans"].items()}
    poses = tmp_path / "other_poses.json"
    poses.write_text(json.dumps(data))
    before = tree(tmp_path)
    res = invoke("tie-to-als", small_sim.manifest_path, "--poses", poses, "--out", tmp_path / "geo")
    assert_one_line_error(res, "other_poses.json", "another manifest")
    assert_nothing_left(tmp_path, before)


def test_failed_tie_to_als_leaves_no_empty_folder(small_sim, tmp_path):
    manifest = write_manifest(tmp_path / "no_als.toml", small_sim, ["P1-S0", "P1-S1"], als=False)
    poses = tmp_path / "poses.json"
    data = json.loads(small_sim.ground_truth_path.read_text())
    poses.write_text(json.dumps({**data, "frame": "plot"}))
    before = tree(tmp_path)
    res = invoke("tie-to-als", manifest, "--poses", poses, "--out", tmp_path / "geo" / "deep")
    assert res.exit_code == 2, res.output
    assert_nothing_left(tmp_path, before)


def test_a_three_point_file_is_named(small_sim, tmp_path):
    from plotmosaic.io.las import PointCloud, write_cloud

    tiny = write_cloud(
        tmp_path / "tiny.laz", PointCloud(np.random.default_rng(0).uniform(0, 5, (3, 3)))
    )
    res = invoke("align", tiny, small_sim.scan_paths["P1-S0"])
    assert_one_line_error(res, str(tiny), "only 3 points")
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        f'[[scans]]\nid = "a"\npath = "{tiny}"\n[[scans]]\nid = "b"\npath = "{small_sim.scan_paths["P1-S0"]}"\n'
    )
    assert_one_line_error(
        invoke("register-plot", manifest, "--out", tmp_path / "reg"), str(tiny), "only 3 points"
    )
    assert not (tmp_path / "reg").exists()


# ---- faults: SIGKILL of register-plot -j 2, resume, damaged cache --------------------------------


def thinned_manifest(tmp_path: Path, sim, scans: list[str], step: int = 4) -> Path:
    """A plot of every `step`-th point of the given scans: the same pairs, registered faster."""
    from plotmosaic.io.las import PointCloud, write_cloud

    lines = ["version = 1", "[[plots]]", 'id = "P1"']
    for sid in scans:
        path = write_cloud(
            tmp_path / "thin" / f"{sid}.laz",
            PointCloud(read_cloud(sim.scan_paths[sid]).xyz[::step]),
        )
        lines += ["[[plots.scans]]", f'id = "{sid}"', f'path = "{path}"', 'kind = "tls"']
    manifest = tmp_path / "thin" / "m.toml"
    manifest.write_text("\n".join(lines) + "\n")
    return manifest


def register_plot_in_own_group(manifest: Path, out: Path, stderr) -> subprocess.Popen:
    """`register-plot -j 2` as a terminal's foreground job: its own process group, so a signal to
    the group reaches the command and its workers, as Ctrl-C does."""
    return subprocess.Popen(
        [*PLOTMOSAIC, "register-plot", str(manifest), "--out", str(out), "-j", "2"],
        stdout=subprocess.DEVNULL,
        stderr=stderr,
        start_new_session=True,
    )


def children(pid: int) -> set[int]:
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.add(int(stat.parent.name))
    return out


def _in_sleep(pid: int) -> bool:
    """The process waits in a timed sleep (Python's time.sleep: the kernel's hrtimer_nanosleep)."""
    try:
        return "nanosleep" in Path(f"/proc/{pid}/wchan").read_text()
    except OSError:
        return False


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def pairs_line(output: str) -> tuple[int, int]:
    m = re.search(r"pairs: (\d+) \((\d+) registered now", output)
    assert m, output
    return int(m.group(1)), int(m.group(2))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.slow
def test_sigkill_register_plot_leaves_no_orphans_and_resumes(small_sim, tmp_path):
    manifest = thinned_manifest(tmp_path, small_sim, ["P1-S0", "P1-S1", "P1-S2"])
    out = tmp_path / "reg"
    proc = register_plot_in_own_group(manifest, out, stderr=subprocess.DEVNULL)
    workers: set[int] = set()

    def first_pair_cached() -> bool:
        workers.update(c for c in children(proc.pid) if alive(c))
        return bool(list((out / "pairs").glob("*.json"))) or proc.poll() is not None

    assert _wait_for(first_pair_cached, 240)
    assert proc.poll() is None, "register-plot finished before it could be killed"
    workers |= {c for c in children(proc.pid) if alive(c)}
    proc.kill()
    proc.wait()
    assert workers, "no worker process was seen"
    # a worker notices its parent is gone within POLL_SECONDS (or at once: PDEATHSIG)
    _wait_for(lambda: not any(alive(w) for w in workers), 3.0)
    orphans = [w for w in workers if alive(w)]
    for w in orphans:
        os.kill(w, signal.SIGKILL)
    assert not orphans, f"orphaned workers: {orphans}"

    done = len(list((out / "pairs").glob("*.json")))
    assert 1 <= done < 3
    res = invoke("register-plot", manifest, "--out", out, "-j", "1")
    assert res.exit_code == 0, res.output
    assert pairs_line(res.output) == (3, 3 - done)  # only the missing pairs were registered again
    assert not [p for p in tree(out) if ".tmp-" in p]

    # a damaged entry (NaN in the transform; a failed pair's entry without its status) is discarded with
    # one warning and registered again
    entry = sorted((out / "pairs").glob("*.json"))[0]
    record = json.loads(entry.read_text())
    if record["status"] == "ok":
        record["transform"][0][3] = float("nan")
    else:
        del record["status"]
    entry.write_text(json.dumps(record))
    res = invoke("register-plot", manifest, "--out", out, "-j", "1")
    assert res.exit_code == 0, res.output
    assert pairs_line(res.output) == (3, 1)
    warnings = [line for line in res.output.splitlines() if line.startswith("warning: ")]
    assert len(warnings) == 1 and entry.name in warnings[0], res.output


POOL_SCRIPT = """
import multiprocessing, sys, time
from concurrent.futures import ProcessPoolExecutor
from plotmosaic.lifetime import bind_to_parent
INIT = bind_to_parent

if __name__ == "__main__":
    pool = ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn"), initializer=INIT)
    futures = [pool.submit(time.sleep, 60) for _ in range(2)]
    print("ready", flush=True)
    time.sleep(120)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_pool_workers_die_with_their_parent(tmp_path):
    script = tmp_path / "pool.py"
    script.write_text(POOL_SCRIPT)
    proc = subprocess.Popen(
        [sys.executable, str(script)], stdout=subprocess.PIPE, text=True, start_new_session=True
    )
    assert proc.stdout.readline().strip() == "ready"

    # the spawned workers (and the resource tracker), each inside its job's sleep: its initializer ran
    def sleeping_workers() -> set[int]:
        return {c for c in children(proc.pid) if alive(c) and _in_sleep(c)}

    assert _wait_for(lambda: len(sleeping_workers()) >= 2, 60)
    workers = sleeping_workers()
    proc.kill()
    proc.wait()
    _wait_for(lambda: not any(alive(w) for w in workers), 3.0)
    orphans = [w for w in workers if alive(w)]
    for w in orphans:
        os.kill(w, signal.SIGKILL)
    assert len(workers) >= 2 and not orphans, (workers, orphans)


# ---- issue 38: one line for every bad input, non-UTF-8 names, leftovers, interrupt windows ------


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_non_finite_manifest_number_is_named(small_sim, tmp_path, value):
    manifest = write_manifest(tmp_path / "m.toml", small_sim, ["P1-S0", "P1-S1"])
    text = manifest.read_text().replace(
        'id = "P1-S1"\n', f'id = "P1-S1"\napprox_position = [{value}, 0.0, 0.0]\n'
    )
    manifest.write_text(text)
    before = tree(tmp_path)
    for args in (("info", manifest), ("register-plot", manifest, "--out", tmp_path / "reg")):
        res = invoke(*args)
        assert_one_line_error(res, "m.toml", "'P1-S1'", "approx_position", "finite")
    assert_nothing_left(tmp_path, before)


def test_a_truncated_scan_stops_register_plot_before_any_pair(small_sim, tmp_path):
    data = small_sim.scan_paths["P1-S2"].read_bytes()
    bad = tmp_path / "BAD.laz"
    bad.write_bytes(data[: len(data) // 2])  # header intact, points cut off
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        f'[[scans]]\nid = "good"\npath = "{small_sim.scan_paths["P1-S0"]}"\n'
        f'[[scans]]\nid = "BAD"\npath = "{bad}"\n'
    )
    res = invoke("register-plot", manifest, "--out", tmp_path / "reg", "-j", "1")
    assert_one_line_error(res, str(bad), "'BAD'", "truncated")  # no progress bar before it
    assert not list((tmp_path / "reg").glob("pairs/*.json")), "a pair ran before the check"


def test_bad_option_values_and_unreadable_files_get_one_line(small_sim, tmp_path):
    src, tgt = small_sim.scan_paths["P1-S1"], small_sim.scan_paths["P1-S0"]
    assert_one_line_error(invoke("align", src, tgt, "--levels-source", "abc"), "--levels-source")
    assert_one_line_error(invoke("align", src, tgt, "--no-such-option"), "--no-such-option")
    assert_one_line_error(invoke("align", src), "'target'")
    assert_one_line_error(invoke("no-such-command"), "no-such-command")
    for args in (("-h",), ("align", "-h"), ("merge", "--help")):
        res = invoke(*args)
        assert res.exit_code == 0 and res.output.startswith("Usage: "), res.output

    unreadable = tmp_path / "locked.laz"
    unreadable.write_bytes(src.read_bytes())
    unreadable.chmod(0)
    # root reads anything: drop the capability that lets it, as a user without it would be
    prefix = ["setpriv", "--inh-caps=-dac_override,-dac_read_search"]
    prefix += ["--bounding-set=-dac_override,-dac_read_search"] if os.geteuid() == 0 else []
    for command in (["info", str(unreadable)], ["align", str(unreadable), str(tgt)]):
        res = subprocess.run([*prefix, *PLOTMOSAIC, *command], capture_output=True, text=True)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1, res.stderr
        assert (
            lines[0].startswith("error: ") and "locked.laz" in lines[0] and "readable" in lines[0]
        )


def test_links_that_go_nowhere_are_named_for_what_they_are(tmp_path):
    (tmp_path / "loop_a.laz").symlink_to(tmp_path / "loop_b.laz")
    (tmp_path / "loop_b.laz").symlink_to(tmp_path / "loop_a.laz")
    (tmp_path / "broken.laz").symlink_to(tmp_path / "gone.laz")
    assert_one_line_error(invoke("info", tmp_path / "loop_a.laz"), "loop_a.laz", "link loop")
    assert_one_line_error(invoke("info", tmp_path / "broken.laz"), "broken symbolic link")
    manifest = tmp_path / "m.toml"
    manifest.write_text('[[scans]]\nid = "a"\npath = "loop_a.laz"\n')
    assert_one_line_error(invoke("info", manifest), "m.toml", "'a'", "link loop")


def test_a_stray_point_far_away_is_named_by_merge_not_blamed_on_the_pose(small_sim, tmp_path):
    las = read_cloud(small_sim.scan_paths["P1-S3"])
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = [0.01, 0.01, 0.01]  # 1 cm integers reach 10,000 km
    header.offsets = np.floor(las.xyz.min(axis=0))
    far = laspy.LasData(header)
    xyz = np.vstack([las.xyz, las.xyz[:1] + [1.0e7, 0.0, 0.0]])
    far.x, far.y, far.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    far.write(tmp_path / "far.laz")
    manifest = write_manifest(tmp_path / "m.toml", small_sim, ["P1-S0", "P1-S3"])
    manifest.write_text(
        manifest.read_text().replace(str(small_sim.scan_paths["P1-S3"]), str(tmp_path / "far.laz"))
    )
    before = tree(tmp_path)
    res = invoke(
        "merge", manifest, "--poses", small_sim.ground_truth_path, "--out", tmp_path / "o" / "m.laz"
    )
    assert_one_line_error(res, "far.laz", "10,000 km", "stray point")
    assert "pose" not in res.output
    assert_nothing_left(tmp_path, before)


def test_the_write_probe_leaves_nothing_on_a_full_disk(tmp_path, monkeypatch):
    from plotmosaic.io import atomic

    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    before = tree(tmp_path)
    with pytest.raises(InputError, match="No space left"):
        atomic.check_output_dir(tmp_path / "new" / "out")
    with pytest.raises(InputError, match="No space left"):
        atomic.check_output_file(tmp_path / "r.json")
    assert_nothing_left(tmp_path, before)


def _non_utf8(folder: Path, name: bytes) -> Path:
    return Path(os.fsdecode(os.path.join(os.fsencode(folder), name)))


@pytest.mark.slow
def test_non_utf8_names_end_to_end(small_sim, tmp_path):
    """A source file, a plot folder and an output with names that are not UTF-8 (as old Windows or
    camera exports make them): the run works, text outputs hold the names escaped."""
    plot = _non_utf8(tmp_path, b"plot_\xe9")
    plot.mkdir()
    manifest = write_manifest(tmp_path / "m.toml", small_sim, ["P1-S0", "P1-S1"], als=False)
    text = manifest.read_text(encoding="utf-8")
    for sid in ("P1-S0", "P1-S1"):
        copy = plot / f"{sid}.laz"
        copy.write_bytes(small_sim.scan_paths[sid].read_bytes())
        text = text.replace(str(small_sim.scan_paths[sid]), f"{sid}.laz")
    (plot / "m.toml").write_text(text, encoding="utf-8")
    out = _non_utf8(tmp_path, b"merged_\xff.laz")
    res = subprocess.run(
        [
            *PLOTMOSAIC,
            "merge",
            plot / "m.toml",
            "--poses",
            small_sim.ground_truth_path,
            "--out",
            out,
        ],
        capture_output=True,
    )
    assert res.returncode == 0, res.stderr
    assert len(laspy.read(out).points) > 0
    json.loads(out.with_name("merged_\udcff.laz.json").read_text())
    assert "\\udcff" in out.with_name("merged_\udcff.config-used.toml").read_text(encoding="utf-8")
    reg = plot / "reg"
    res = subprocess.run(
        [*PLOTMOSAIC, "register-plot", plot / "m.toml", "--out", reg, "-j", "1"],
        capture_output=True,
    )
    assert res.returncode == 0, res.stderr
    assert b"plot_\\udce9" in res.stdout and (reg / "report.html").is_file()
    assert set(json.loads((reg / "poses.json").read_text())["scans"]) == {"P1-S0", "P1-S1"}


@pytest.mark.slow
def test_align_with_a_non_utf8_name_and_sigterm_as_it_exits(small_sim, tmp_path):
    """The summary printed, SIGTERM lands while the process exits: 0 or 130, never the default
    action's 143 or a traceback; a source name that is not UTF-8 is printed escaped."""
    source = _non_utf8(tmp_path, b"scan_\xff\xfe.laz")
    source.write_bytes(small_sim.scan_paths["P1-S1"].read_bytes())
    target = tmp_path / "same.laz"  # the same cloud: the fine stage from identity is quick
    target.write_bytes(small_sim.scan_paths["P1-S1"].read_bytes())
    out = tmp_path / "r.json"
    proc = subprocess.Popen(
        [*PLOTMOSAIC, "align", source, target, "--no-coarse", "--out", out],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if b"settings used" in line:
            proc.send_signal(signal.SIGTERM)
            break
    rest, err = proc.communicate(timeout=120)
    assert proc.returncode in (0, 130), (proc.returncode, err)
    assert b"Traceback" not in err and b"Error" not in err, err
    assert b"scan_\\udcff\\udcfe.laz" in seen[0], seen
    assert json.loads(out.read_text())["fitness"] > 0.99
    assert "\\udcff" in (tmp_path / "r.config-used.toml").read_text(encoding="utf-8")


def _group_alive(pgid: int) -> list[int]:
    return [
        int(p.parent.name)
        for p in Path("/proc").glob("[0-9]*/stat")
        if _pgid(p) == pgid and alive(int(p.parent.name))
    ]


def _pgid(stat: Path) -> int | None:
    try:
        return int(stat.read_text().rsplit(")", 1)[1].split()[2])
    except (OSError, IndexError, ValueError):
        return None


def _workers(pid: int) -> list[int]:
    """The spawned pool workers among the children (not the resource tracker)."""
    found = []
    for child in children(pid):
        try:
            if b"--multiprocessing-fork" in Path(f"/proc/{child}/cmdline").read_bytes():
                found.append(child)
        except OSError:
            continue
    return found


def _ignores_sigint(pid: int) -> bool:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigIgn:"):
            return bool(int(line.split()[1], 16) & (1 << (signal.SIGINT - 1)))
    return False


def _wait_for(condition, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("moment", ["workers starting", "first scan prepared"])
def test_ctrl_c_in_the_first_seconds_of_the_worker_pool(small_sim, tmp_path, moment):
    """Ctrl-C reaches the whole process group, workers still importing included: one line
    `interrupted`, exit 130, no traceback from any worker, no process left."""
    manifest = thinned_manifest(tmp_path, small_sim, ["P1-S0", "P1-S1", "P1-S2"])
    out = tmp_path / "reg"
    proc = register_plot_in_own_group(manifest, out, stderr=subprocess.PIPE)
    if moment == "workers starting":  # both spawned, the parent past its forks, workers importing
        ready = lambda: len(_workers(proc.pid)) >= 2 and not _ignores_sigint(proc.pid)  # noqa: E731
    else:
        ready = lambda: any((out / "prepared").glob("*.npz"))  # noqa: E731
    assert _wait_for(lambda: ready() or proc.poll() is not None, 240)
    assert proc.poll() is None, "register-plot ended before the interrupt"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    lines = [ln for ln in err.decode(errors="replace").splitlines() if ln.strip()]
    assert proc.returncode == 130 and lines == ["interrupted"], (proc.returncode, lines)
    assert _wait_for(lambda: not _group_alive(proc.pid), 10), _group_alive(proc.pid)
