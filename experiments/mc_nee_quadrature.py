"""The Monte Carlo's own elevation quadrature at the far edge: is the 64x misfit in the reference? (issue 14)

The Monte Carlo scores every diffuse event's light at the aperture by next-event estimation over ``nee_points``
elevation nodes across the guided band (``MCOptions.nee_points``; 24 in ``experiments/eval_mc_data.py``'s runs). A
far-edge return is then a sum over that many discrete delays, which a 64x capture could resolve. Next-event
estimation draws no random numbers, so the same seed with more nodes follows the same paths: the difference is the
quadrature alone. This script runs the calibration baseline of ``eval_mc_data.py`` (25,000 packets per sensor, the
guided scene) with ``--nodes`` (default 24 and 96) on ``--seeds`` seeds, and reports the difference against the
photon noise of a capture at 1x, 16x and 64x (its excess chi-square, whole and in the far edge's window) and per
sensor relative to the coarser run around the far edge.

All data **simulated** (tofjax's Monte Carlo). About 1.5 minutes at 8 seeds on the 2-core VM.

    python experiments/mc_nee_quadrature.py --out docs/results/mc_nee_quadrature.json
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: the far edge's window (bins), as near_field_aperture.py's WINDOWS
FAR_EDGE = (46, 62)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON file to write")
    ap.add_argument("--seeds", type=int, default=8, help="Monte Carlo seeds per quadrature (default 8)")
    ap.add_argument("--nodes", default="24,96", help="two next-event node counts, comma-separated (default 24,96)")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    import tofjax
    from tofjax.outputs import OutputError, check_output

    try:
        nodes = [int(x) for x in a.nodes.split(",")]
        if len(nodes) != 2 or min(nodes) < 1:
            raise ValueError(f"--nodes: expected two node counts >= 1, got {a.nodes!r}")
        if a.seeds < 1:
            raise ValueError(f"--seeds: must be >= 1, got {a.seeds}")
        path = check_output(Path(a.out), overwrite=a.overwrite)
    except (OutputError, ValueError) as e:
        ap.exit(2, f"error: {e}\n")
    tofjax.enable_x64()
    sys.path.insert(0, str(HERE))
    import eval_mc_data as ev
    from tofjax.mc.capture import mc_expected_counts

    scene = ev.guided_scene()
    result = ev.study_header("the Monte Carlo's next-event elevation quadrature at the far edge, same paths",
                             "simulated (tofjax.mc Monte Carlo runs, as experiments/eval_mc_data.py)")
    t0 = time.perf_counter()
    mean = {}
    for m in nodes:
        runs = [mc_expected_counts(scene, dataclasses.replace(ev.mc_options(25_000, s), nee_points=m))[0]
                for s in range(a.seeds)]
        mean[m] = np.mean(runs, 0)
        print(f"{m} nodes: {a.seeds} runs", flush=True)
    coarse, fine = mean[nodes[0]], mean[nodes[1]]
    d = fine - coarse
    lo, hi = FAR_EDGE
    result |= {"seeds": a.seeds, "nodes": nodes, "far_edge_bins": [lo, hi],
               "same_paths_first_12_bins_equal": bool(np.allclose(coarse[..., :12], fine[..., :12]))}
    for e in (1, 16, 64):
        chi = (d * e) ** 2 / np.maximum(coarse * e, 1.0)  # the difference against the capture's photon noise
        result[f"excess_chi2_of_the_difference_{e}x"] = {"all": float(chi.sum()), "far_edge": float(chi[..., lo:hi].sum()),
                                                          "bins": int(chi.size)}
        print(f"{e}x: the difference's chi-square {chi.sum():.0f} over {chi.size} bins, far edge {chi[..., lo:hi].sum():.0f}")
    rel = d.sum(1)[:, lo - 6:hi + 4] / coarse.sum(1)[:, lo - 6:hi + 4]
    result["fine_minus_coarse_over_coarse_per_sensor"] = {"bins": [lo - 6, hi + 4], "values": rel.round(5).tolist(),
                                                          "largest": float(np.abs(rel).max())}
    print(f"largest relative difference per sensor around the far edge: {np.abs(rel).max():.4f}")
    result["seconds"] = time.perf_counter() - t0
    ev.write_study(result, path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
