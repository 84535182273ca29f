"""register-plot's growth rounds: the pairs a plot in pieces adds (no registration involved)."""

from plotmosaic.config.register import RegisterConfig
from plotmosaic.manifest import Manifest, Plot, Scan
from plotmosaic.stages.register_plot.grow import grow_jobs, plot_pair
from plotmosaic.stages.register_plot.pairs import Pairs, pair_settings


def _plot_of(root, n: int) -> tuple[Manifest, Plot]:
    """A manifest of one plot of `n` scans, each file a few distinct bytes (pair keys hash them)."""
    scans = []
    for k in range(n):
        (root / f"s{k}.laz").write_bytes(bytes([k]) * 10)
        scans.append(Scan(id=f"s{k}", path=f"s{k}.laz"))
    plot = Plot(id="P", scans=scans)
    return Manifest(plots=[plot], source=root / "m.toml"), plot


def test_a_plot_in_pieces_grows_its_ranked_partners_with_the_later_scan_as_source(tmp_path):
    manifest, plot = _plot_of(tmp_path, 4)
    config = RegisterConfig()
    settings = pair_settings(config, 0, tmp_path)
    done = [plot_pair(settings, manifest, plot, pair, {}) for pair in [("s2", "s1"), ("s3", "s2")]]
    records = {j.key: {"status": "ok"} for j in done}
    # s0 is a piece of its own; its ranked partner s2 comes later in the plot
    pairs = Pairs(jobs=done, records=records, computed=0)
    jobs = grow_jobs(manifest, config, settings, {}, {"s0": ["s2", "s1"]}, pairs)
    expected = [
        plot_pair(settings, manifest, plot, (s, "s0"), {})
        for s in ["s2", "s1"][: config.signature.grow_per_scan]
    ]
    assert jobs == expected and all(j.source != "s0" for j in jobs)
    joined = plot_pair(settings, manifest, plot, ("s1", "s0"), {})
    records[joined.key] = {"status": "ok"}
    ranks = {"s0": ["s2", "s1"]}
    pairs = Pairs(jobs=[*done, joined], records=records, computed=0)
    assert grow_jobs(manifest, config, settings, {}, ranks, pairs) == []
