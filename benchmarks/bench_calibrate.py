"""Calibrate the shipped real AirSAS scan by autofocus (``recon.calibrate``) and check the
result with the product backprojector.

The scan has one sonar height, so a horizontal image plane at the wrong height defocuses the
same way as a wrong time offset: the focus S(z, δt) has a ridge, not a peak (printed first,
``--ridge``). For each image height and each set of free parameters: the L-BFGS-B fit (AD
gradient), its focus before/after and the curvature of −log S at the optimum; then the
corrected scan (``recon.calibrate.apply``) backprojected by
:func:`recon.backprojection.backproject` (an independent implementation) and its sharpness.

    python benchmarks/bench_calibrate.py --out results.json
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", type=int, default=96, help="image pixels per side (default 96)")
    ap.add_argument("--half-width", type=float, default=0.125, help="image half width (m)")
    ap.add_argument("--heights", type=float, nargs="+", default=(0.0, 0.1, 0.2, 0.25),
                    help="image-plane heights (m); z = 0 is the reference's image plane")
    ap.add_argument("--fits", default="time_offset",
                    help="free-parameter sets fitted at every height, ';'-separated")
    ap.add_argument("--full-at", type=float, default=0.2,
                    help="height where every parameter is also fitted (time_offset,rig_offset "
                         "and sound_speed,time_offset,rig_offset, with curvature)")
    ap.add_argument("--ridge-heights", type=float, nargs="*",
                    default=(0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3))
    ap.add_argument("--ridge-us", type=float, nargs="*",
                    default=(-100, -75, -50, -25, 0, 25, 50, 75, 100))
    ap.add_argument("--max-evaluations", type=int, default=40)
    args = ap.parse_args(argv)
    from sonarsim import data
    from recon import backprojection, calibrate
    from recon.grid import Grid
    ds = data.real_scan()
    h = args.half_width

    def grid_at(z):
        return Grid([[-h, h], [-h, h], [z, z]], (args.size, args.size, 1))

    results = {"size": args.size, "half_width": h, "ridge": [], "fits": []}
    t0 = time.perf_counter()
    for z in args.ridge_heights:
        problem = calibrate.FocusProblem(ds, grid_at(z))
        row = [problem.focus(calibrate.Calibration(time_offset=us * 1e-6)) for us in args.ridge_us]
        results["ridge"].append({"z": z, "time_offset_us": list(args.ridge_us), "focus": row})
        print(f"ridge z={z:.3f}: " + " ".join(f"{us:+.0f}us:{s:.3f}"
                                              for us, s in zip(args.ridge_us, row)), flush=True)
    results["ridge_wall_s"] = time.perf_counter() - t0

    def product_focus(grid, cal):
        vol = backprojection.backproject(calibrate.apply(ds, cal), grid, upsample=4,
                                         progress=False)
        return calibrate.sharpness(vol)

    jobs = [(z, spec, False) for z in args.heights for spec in args.fits.split(";")]
    jobs += [(args.full_at, "time_offset,rig_offset", True),
             (args.full_at, "sound_speed,time_offset,rig_offset", True)]
    for z, spec, curvature in jobs:
        grid = grid_at(z)
        t0, c0 = time.perf_counter(), time.process_time()
        res = calibrate.fit(ds, grid, free=spec, max_evaluations=args.max_evaluations,
                            curvature=curvature)
        row = {"z": z, **res.as_dict(), "main_thread_cpu_s": time.process_time() - c0,
               "wall_s": time.perf_counter() - t0,
               "product_bp_focus_before": product_focus(grid, calibrate.Calibration()),
               "product_bp_focus_after": product_focus(grid, res.calibration)}
        print(json.dumps(row), flush=True)
        results["fits"].append(row)
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
