"""The run's one interactive 3D view (view3d.html): the thinned placed scans, one colour per scan,
and the ALS as a layer a click on its legend entry hides or shows.

plotly.js is inlined once in this one page (it opens offline, from its file); the points are
thinned to the `[report]` size cap, so the page stays under view3d_max_mb."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.config.report import ReportConfig
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.report.collect import als_under, sample
from plotmosaic.report.pictures import scan_colours

BYTES_PER_POINT = 21  # three float32 coordinates as plotly writes them (base64), with the framing
ALS_AROUND = 10.0  # ALS shown this far (m) around the scans: the ground they stand on


def _rgb(c) -> str:
    return f"rgb({c[0] * 255:.0f},{c[1] * 255:.0f},{c[2] * 255:.0f})"


def _trace(go, name: str, xyz: np.ndarray, origin: np.ndarray, colour: str, size: float):
    q = (xyz - origin).astype(np.float32)
    return go.Scatter3d(
        x=q[:, 0],
        y=q[:, 1],
        z=q[:, 2],
        mode="markers",
        name=name,
        marker={"size": size, "color": colour},
    )


def _figure(go, clouds: dict[str, np.ndarray], als: np.ndarray | None, origin: np.ndarray):
    colours = scan_colours(list(clouds))
    fig = go.Figure()
    if als is not None and len(als):
        fig.add_trace(_trace(go, "ALS (click to hide)", als, origin, "rgb(150,150,150)", 1.5))
    for s, p in clouds.items():
        fig.add_trace(_trace(go, s, p, origin, _rgb(colours[s]), 1))
    fig.update_layout(
        scene={"aspectmode": "data"},
        title=f"placed scans, thinned (origin {origin[0]:.0f}, {origin[1]:.0f}, {origin[2]:.0f})",
        margin={"l": 0, "r": 0, "t": 40, "b": 0},
        legend={"itemsizing": "constant"},
    )
    return fig


def _budget(cfg: ReportConfig, n_clouds: int, js_bytes: int) -> int:
    """Points per cloud that keep the page under the cap."""
    room = max(0.0, cfg.view3d_max_mb * 1e6 - js_bytes) / BYTES_PER_POINT
    total = min(cfg.view3d_total, int(room))
    return max(0, min(cfg.view3d_points, total // max(1, n_clouds)))


def write_3d_view(
    path: Path,
    clouds: dict[str, np.ndarray],
    als_xyz: np.ndarray | None,
    cfg: ReportConfig,
    seed: int,
) -> Path | None:
    """view3d.html of the placed clouds and the ALS under them; None without plotly, without
    points, or when even the thinned page would pass the cap."""
    if not clouds or cfg.view3d_points == 0:
        return None
    try:  # optional and heavy: only the 3D view needs it
        import plotly.graph_objects as go
        from plotly.offline import get_plotlyjs
    except ImportError:
        return None
    js = len(get_plotlyjs())
    n = len(clouds) + (als_xyz is not None)
    per = _budget(cfg, n, js)
    if per < 100:
        return None
    origin = np.floor(np.min([p.min(axis=0) for p in clouds.values()], axis=0))
    small = sample(clouds, per, seed)
    als = (
        None
        if als_xyz is None
        else sample({"ALS": als_under(als_xyz, clouds, ALS_AROUND)}, per, seed)["ALS"]
    )
    text = _figure(go, small, als, origin).to_html(include_plotlyjs=True, full_html=True)
    if len(text) > cfg.view3d_max_mb * 1e6:
        return None
    return write_text_atomic(path, text)
