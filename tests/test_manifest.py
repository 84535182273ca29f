"""Manifests: both forms load, and every mistake names file, plot, scan and field."""

from pathlib import Path

import numpy as np
import pytest
from helpers import pair_prior

from plotmosaic.errors import InputError
from plotmosaic.io import PointCloud, write_cloud
from plotmosaic.manifest import dump_manifest, load_manifest


@pytest.fixture
def scans(tmp_path):
    rng = np.random.default_rng(0)
    for name in ("a", "b", "c"):
        write_cloud(tmp_path / f"{name}.laz", PointCloud(rng.uniform(-5, 5, (200, 3))))
    return tmp_path


ONE_PLOT = """
plot_id = "P1"
crs = "EPSG:26912"
[[scans]]
id = "c"
path = "c.laz"
kind = "tls"
[[scans]]
id = "a"
path = "a.laz"
reference = true
approx_position = [1.0, 2.0, 0.0]
"""

REGION = """
name = "two plots"
[[als]]
path = "c.laz"
[[plots]]
id = "P1"
[[plots.scans]]
id = "P1-A"
path = "a.laz"
[[plots]]
id = "P2"
crs = "EPSG:26912"
[[plots.scans]]
id = "P2-B"
path = "b.laz"
kind = "mls"
levels = 2
"""


def write(tmp: Path, text: str, name="m.toml") -> Path:
    (tmp / name).write_text(text)
    return tmp / name


def test_one_plot_form(scans):
    m = load_manifest(write(scans, ONE_PLOT))
    assert [p.id for p in m.plots] == ["P1"]
    assert m.plots[0].reference.id == "a"
    assert m.scan("c").k == 3 and m.scan("a").approx_position == (1.0, 2.0, 0.0)
    assert m.resolve(m.scan("c").path) == scans / "c.laz"


def test_region_form_and_dump_round_trip(scans):
    m = load_manifest(write(scans, REGION))
    assert [s.id for s in m.scans] == ["P1-A", "P2-B"]
    assert m.scan("P2-B").k == 2 and m.als[0].k == 2 and m.plot_of("P2-B").crs == "EPSG:26912"
    again = load_manifest(write(scans, dump_manifest(m), "again.toml"))
    assert again.model_dump(exclude={"source"}) == m.model_dump(exclude={"source"})


@pytest.mark.parametrize(
    "text, expected",
    [
        (ONE_PLOT.replace('kind = "tls"', 'kind = "sonar"'), "scan 'c', field 'kind'"),
        (
            ONE_PLOT.replace("approx_position = [1.0, 2.0, 0.0]", 'approx_position = "here"'),
            "scan 'a', field 'approx_position'",
        ),
        (REGION.replace("levels = 2", 'levels = "two"'), "plot 'P2', scan 'P2-B', field 'levels'"),
        (REGION.replace('id = "P2-B"', 'id = "P1-A"'), "duplicate scan id 'P1-A'"),
        (
            ONE_PLOT.replace('path = "c.laz"', 'path = "missing.laz"'),
            "scan 'c', field 'path': file not found",
        ),
        (ONE_PLOT + "colour = 3\n", "field 'colour': Extra inputs are not permitted"),
        (ONE_PLOT.replace('crs = "EPSG:26912"', 'crs = "EPSG:99999999"'), "plot 'P1', field 'crs'"),
        ("[[scans]\n", "not valid TOML"),
        (
            ONE_PLOT.replace('id = "c"\n', 'id = "c"\nreference = true\n'),
            "more than one reference scan",
        ),
    ],
)
def test_invalid_manifests_name_the_field(scans, text, expected):
    path = write(scans, text)
    with pytest.raises(InputError) as err:
        load_manifest(path)
    message = str(err.value)
    assert str(path) in message and expected in message
    assert "\n" not in message


@pytest.mark.parametrize(
    "field, value",
    [
        ("plot_id", "../../escaped"),
        ("plot_id", "a/b"),
        ("plot_id", ".."),
        ("id", "../s"),
        ("id", "x\\\\y"),
    ],
)
def test_ids_that_would_escape_the_output_folder(scans, field, value):
    from helpers import assert_one_line_error, invoke

    plot_id, scan_id = (value, "a") if field == "plot_id" else ("P1", value)
    text = f'plot_id = "{plot_id}"\n[[scans]]\nid = "{scan_id}"\npath = "a.laz"\n'
    result = invoke("info", write(scans, text))
    assert_one_line_error(result, "m.toml", f"field '{field}'", "not allowed")


def test_safe_ids_and_bom(scans):
    m = load_manifest(
        write(scans, '\ufeffplot_id = "P1.v2_a-b"\n[[scans]]\nid = "S.0_x-1"\npath = "a.laz"\n')
    )
    assert m.plots[0].id == "P1.v2_a-b" and m.scans[0].id == "S.0_x-1"
    raw = scans / "bom.toml"
    raw.write_bytes(b"\xef\xbb\xbf" + REGION.encode())
    assert [p.id for p in load_manifest(raw).plots] == ["P1", "P2"]


@pytest.mark.parametrize(
    "extra, field",
    [("scan = 1\n", "scan"), ("use_pose = true\n", "use_pose"), ("scan = -1\n", "scan")],
)
def test_e57_fields_on_other_files_name_the_field(scans, extra, field):
    path = write(scans, 'plot_id = "P1"\n[[scans]]\nid = "a"\npath = "a.laz"\n' + extra)
    with pytest.raises(InputError) as err:
        load_manifest(path)
    assert str(path) in str(err.value) and f"field '{field}'" in str(err.value)


def test_e57_scan_dump_round_trip(tmp_path):
    """scan (index or name) and use_pose survive dump_manifest; the loaded path names the scan."""
    import pye57

    rng = np.random.default_rng(1)
    with pye57.E57(str(tmp_path / "p.e57"), mode="w") as e57:
        for name in ("north", "south"):
            xyz = rng.uniform(-5, 5, (100, 3))
            e57.write_scan_raw(
                {"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]},
                name=name,
            )
    m = load_manifest(
        write(
            tmp_path,
            'plot_id = "P"\n'
            '[[scans]]\nid = "n"\npath = "p.e57"\nscan = "north"\nuse_pose = true\n'
            '[[scans]]\nid = "s"\npath = "p.e57"\nscan = 1\n',
        )
    )
    assert [s.path.name for s in m.scans] == ["p.e57#0", "p.e57#1"] and m.scan("n").use_pose
    again = load_manifest(write(tmp_path, dump_manifest(m), "again.toml"))
    assert again.model_dump(exclude={"source"}) == m.model_dump(exclude={"source"})
    assert 'scan = "north"' in dump_manifest(m) and 'path = "p.e57"' in dump_manifest(m)


def test_stored_poses_skip_plots_that_store_only_identity(tmp_path):
    """Identity everywhere (what many exports write) is no prior; one real pose beside identity is."""
    import pye57

    rng = np.random.default_rng(4)
    T = np.eye(4)
    T[:3, 3] = [5.0, -2.0, 0.5]
    for name, second in (("ident.e57", np.zeros(3)), ("posed.e57", T[:3, 3])):
        with pye57.E57(str(tmp_path / name), mode="w") as e57:
            for t in (np.zeros(3), second):
                xyz = rng.uniform(-5, 5, (100, 3))
                data = {"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]}
                e57.write_scan_raw(data, rotation=np.array([1.0, 0, 0, 0]), translation=t)
    scan = '[[scans]]\nid = "s{i}"\npath = "FILE"\nscan = {i}\nuse_pose = true\n'
    text = 'plot_id = "P"\n' + "".join(scan.format(i=i) for i in (0, 1))
    ident = load_manifest(write(tmp_path, text.replace("FILE", "ident.e57"), "i.toml"))
    assert ident.stored_poses() == {} and pair_prior(ident, "s1", "s0") is None
    posed = load_manifest(write(tmp_path, text.replace("FILE", "posed.e57"), "p.toml"))
    assert sorted(posed.stored_poses()) == ["s0", "s1"]
    np.testing.assert_allclose(pair_prior(posed, "s1", "s0"), T, atol=1e-12)
    np.testing.assert_allclose(pair_prior(posed, "s0", "s1"), np.linalg.inv(T), atol=1e-12)
