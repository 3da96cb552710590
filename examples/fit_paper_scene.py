"""Fit the paper's scene: one pan scan of a pole, a plane and a rod (Kuc 2003, Fig. 5).

A panning transducer at the origin scans -40..40 deg in 0.3 deg steps (one ping per
angle) in the simulated scene of maps/paper_fig5.geojson; sonarloc segments the scan
into U-shaped TOF curves and fits eq. 3 to each. Printed next to the paper's numbers
(PHYSICS.md); with --plot, the scan and its fitted curves in the style of Fig. 5.

    python examples/fit_paper_scene.py [--seed 7] [--plot out/fig5.png]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from sonarloc.fit.landmarks import fit_scan
from sonarloc.maps.geojson import load_map
from sonarloc.world.rig import PanRig
from sonarloc.world.simulate import simulate_scan

SCENE = Path(__file__).resolve().parents[1] / "maps" / "paper_fig5.geojson"
# the paper's Table (PHYSICS.md): object -> (range m, bearing deg, kappa us, fitted Tm us)
PAPER = {"pole": (1.462, -17.0, 0.67, 8523.0), "plane": (1.500, 4.0, 0.15, 8746.0),
         "rod": (1.471, 22.0, 2.68, 8583.0)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=7, help="random seed (default %(default)s)")
    parser.add_argument("--plot", help="also draw the scan with its fits (PNG)")
    args = parser.parse_args(argv)

    scene = load_map(SCENE)
    scan = simulate_scan(scene, PanRig(pan_deg=(-40.0, 40.0, 0.3)), at=(0.0, 0.0, 0.0),
                         seed=args.seed).readings
    report = fit_scan(scan)
    print(f"{len(scan)} pings, {int((scan.tof_us == scan.tof_us).sum())} echoes, "
          f"{len(report.landmarks)} segments fitted")
    print(f"{'object':6}  {'range m':>8} {'paper':>6}  {'bearing':>8} {'paper':>6}  "
          f"{'kappa us':>8} {'paper':>6}  {'tier':6} status")
    for lm in sorted(report.landmarks, key=lambda lm: lm.bearing_rad):
        bearing = math.degrees(lm.bearing_rad)
        name = min(PAPER, key=lambda k: abs(PAPER[k][1] - bearing))
        r, b, k, _ = PAPER[name]
        print(f"{name:6}  {lm.range_m:8.4f} {r:6.3f}  {bearing:8.2f} {b:6.1f}  "
              f"{lm.kappa_us:8.2f} {k:6.2f}  {lm.tier:6} {lm.status.value}")
    if args.plot:
        from sonarloc.report.plots import draw_scan, require_matplotlib

        plt = require_matplotlib()
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        draw_scan(ax, scan.x_m, scan.y_m, scan.yaw_rad, scan.tof_us, report.landmarks)
        ax.legend(fontsize=7, loc="upper left")
        ax.set_title("the paper's scene (Fig. 5): pole, plane, rod at 1.5 m", fontsize=9)
        Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=130)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
