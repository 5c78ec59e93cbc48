"""The inversion's part of ``make demo``: a six-contact frame on the default scene, its
tactile map (full method) as a PNG, and the detection table. Costs a few seconds."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..capture import Capture
from ..scene import Touch
from .correction import OpticalParams
from .detect import match
from .pipeline import InvertOptions, build_inverter
from .synth import shadowed
from .plots import plot_map_grid

__all__ = ["SIX_CONTACTS", "run"]

#: Six contacts spread over the surface (seed 000 Fig. 6, bottom; configs/touch-six.toml).
SIX_CONTACTS = ((0.07, 0.08), (0.22, 0.06), (0.15, 0.15), (0.06, 0.24), (0.24, 0.22), (0.13, 0.27))


def run(out_dir: str | Path, baseline: Capture, *, seed: int = 0, optical: OpticalParams | None = None) -> list[str]:
    """Simulate one six-contact frame of ``baseline``'s scene, map it with the baseline-only
    and the full method (with the calibrated ``optical`` parameters if given), write
    ``tactile_map.png`` and return summary lines."""
    from ..simulate import simulate

    out = Path(out_dir)
    scene = baseline.scene.without_touches()
    six = scene.replace(touches=tuple(Touch(p, 0.006, 1.0) for p in SIX_CONTACTS), name=f"{scene.name}+6 touches")
    frame = simulate(six, 1, seed)
    truth = np.array(SIX_CONTACTS)
    cells, lines = [], []
    results = {}
    for method in ("baseline", "full"):
        inv = build_inverter(
            scene, baseline.mean(), InvertOptions(method=method), optical, n_baseline=baseline.n_frames
        )
        res = inv.process(frame.histograms)
        results[method] = (inv, res)
        cells.append({"map": res.maps[0], "detection": res.detections[0], "truth": truth})
    path = plot_map_grid(
        [cells],
        results["full"][0].grid,
        six,
        out / "tactile_map.png",
        col_titles=["baseline removal only", "full (Algorithm 1)"],
        size=4.5,
    )
    lines.append(
        f"touch inversion: {len(SIX_CONTACTS)} contacts (simulated), tactile maps in {path.name} (crosses: detections, dashed: truth)"
    )
    if optical is not None:
        lines.append(f"  optics from the calibration: n1 = {optical.n1:.5f}, mu_s + mu_a = {optical.mu_s_per_m + optical.mu_a_per_m:.3f} /m")
    for method, (inv, res) in results.items():
        det = res.detections[0]
        k, d = match(det.positions(), truth)
        err = f", mean error {100 * d.mean():.2f} cm" if k else ""
        lines.append(
            f"  {method:9s}: {len(det.touches)} detections, {k} of {len(truth)} contacts found within 2 cm{err}"
        )
    lines.append("  full method detections:   x [cm]   y [cm]   strength   nearest true contact [cm]")
    for t in sorted(results["full"][1].detections[0].touches, key=lambda t: (t["y_m"], t["x_m"])):
        dist = np.hypot(*(truth - [t["x_m"], t["y_m"]]).T).min()
        lines.append(
            f"                          {100 * t['x_m']:6.1f}   {100 * t['y_m']:6.1f}   {t['strength']:8.2f}   {100 * dist:6.2f}"
        )
    det = results["full"][1].detections[0]
    shadow = shadowed(scene, truth)
    for i, p in enumerate(truth):
        if not len(det.touches) or np.hypot(*(det.positions() - p).T).min() > 0.02:
            why = (
                "shadowed: every sensor that sees it has another contact in front, in the same zone"
                if shadow[i]
                else "not shadowed"
            )
            lines.append(f"  missed by full: ({100 * p[0]:.1f}, {100 * p[1]:.1f}) cm, {why}")
    lines.append("")
    return lines
