"""`make demo`: mesh scene -> transients -> sonar dataset -> reconstruction -> pictures.

Runs the real command-line tools in order on a small problem (a few hundred poses of a
shipped scene) and, when the real AirSAS scan is beside the project, imports it and
backprojects it too. Everything lands in one output folder with a SUMMARY.txt.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
from pathlib import Path

from recon.cli import main as recon_main
from sonarsim.cli import main as sonarsim_main

# The ground-truth meshes have no ground plane; evaluate above it (docs/evaluation.md).
ABOVE_GROUND = ["--crop", "-0.2", "0.2", "-0.2", "0.2", "0.005", "0.3"]
SHARED_SCAN = Path(__file__).resolve().parents[2] / "shared" / "data" / "airsas_real"


# Commands that refuse to replace an existing output without --force (a demo re-run
# replaces its own outputs).
REPLACES = {"render", "simulate", "import-airsas", "backproject", "gd", "export", "compare"}


def step(log: list[str], title: str, tool, argv: list[str]) -> str:
    """Run one CLI call, echo it, keep its stdout for the summary; stop on failure."""
    if argv[0] in REPLACES:
        argv = [*argv, "--force"]
    print(f"\n== {title}\n$ {tool.__module__.split('.')[0]} {' '.join(argv)}", flush=True)
    out = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out):
        code = tool(argv)
    text = out.getvalue()
    print(text, end="")
    if code:
        raise SystemExit(f"demo step failed ({title}), exit status {code}")
    log.append(f"## {title}  ({time.perf_counter() - t0:.1f} s)\n"
               f"$ {tool.__module__.split('.')[0]} {' '.join(argv)}\n{text}")
    return text


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("demo_out"))
    parser.add_argument("--scene", default="tabletop", help="shipped scene name or TOML file")
    parser.add_argument("--poses", default="cylindrical:120:6",
                        help="trajectory (default: 120 angles x 6 heights = 720 poses)")
    parser.add_argument("--paths-per-pose", type=int, default=4000,
                        help="paths per pose of the transients render (default 4000)")
    parser.add_argument("--mc-snr-db", type=float, default=30.0,
                        help="Monte-Carlo SNR after matched filtering of the simulated "
                             "dataset (default 30 dB, simulate's default)")
    args = parser.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    log: list[str] = []
    t_start = time.perf_counter()
    common = [args.scene, "--poses", args.poses, "--seed", "1"]

    step(log, "render per-bounce transients", sonarsim_main,
         ["render", *common, "--paths-per-pose", str(args.paths_per_pose),
          "--out", str(out / "transients.h5")])
    step(log, "picture of the transients", sonarsim_main,
         ["plot", str(out / "transients.h5"), "--out", str(out / "transients")])
    step(log, "simulate an AirSAS-style dataset (20 kHz LFM, 20 dB total SNR, Monte-Carlo "
              f"SNR {args.mc_snr_db:g} dB)", sonarsim_main,
         ["simulate", *common, "--pulse", "lfm-20k", "--snr-db", "20", "--restart",
          "--mc-snr-db", str(args.mc_snr_db),
          "--out", str(out / "dataset.h5")])
    step(log, "dataset summary", sonarsim_main, ["info", str(out / "dataset.h5")])
    step(log, "echo images, pulse, trajectory", sonarsim_main,
         ["plot", str(out / "dataset.h5"), "--out", str(out / "dataset")])
    step(log, "coherent backprojection", recon_main,
         ["backproject", str(out / "dataset.h5"), "--shape", "64", "64", "48",
          "--out", str(out / "bp.h5")])
    step(log, "gradient descent on complex voxels", recon_main,
         ["gd", str(out / "dataset.h5"), "--shape", "64", "64", "48", "--iterations", "300",
          "--seed", "1", "--out", str(out / "gd.h5")])
    for name in ("bp", "gd"):
        step(log, f"export {name}: MIPs and marching-cubes mesh", recon_main,
             ["export", str(out / f"{name}.h5"), "--mip", str(out / f"{name}_mip.png"),
              "--exr", str(out / f"{name}_mip.exr"), "--mesh", str(out / f"{name}.ply")])
        step(log, f"evaluate {name} against the ground truth", recon_main,
             ["evaluate", str(out / f"{name}.h5"), "--gt", str(out / "dataset.h5"), *ABOVE_GROUND])
    step(log, "side-by-side comparison", recon_main,
         ["compare", str(out / "bp.h5"), str(out / "gd.h5"), "--gt", str(out / "dataset.h5"),
          *ABOVE_GROUND, "--out", str(out / "compare.png")])

    if SHARED_SCAN.is_dir():
        scan, bg = SHARED_SCAN / "small_features_cutout_5k", SHARED_SCAN / "bg_5k"
        step(log, "import the real AirSAS scan (5 kHz LFM, background subtracted)",
             sonarsim_main, ["import-airsas", str(scan), "--background", str(bg),
                             "--out", str(out / "airsas_real.h5")])
        step(log, "backproject the real scan on a 2-D grid at z = 0", recon_main,
             ["backproject", str(out / "airsas_real.h5"), "--bounds", "-0.3", "0.3", "-0.3",
              "0.3", "0", "0", "--shape", "200", "200", "1", "--out", str(out / "airsas_bp.h5")])
        step(log, "export the real-scan image", recon_main,
             ["export", str(out / "airsas_bp.h5"), "--mip", str(out / "airsas_bp.png")])
        # A one-height scan has no elevation resolution; GD fits a thin slab around z = 0
        # (a single voxel layer is met by too few of the forward model's rays).
        step(log, "gradient descent on the real scan (thin slab around z = 0)", recon_main,
             ["gd", str(out / "airsas_real.h5"), "--bounds", "-0.3", "0.3", "-0.3", "0.3",
              "-0.02", "0.02", "--shape", "150", "150", "5", "--iterations", "200",
              "--seed", "1", "--out", str(out / "airsas_gd.h5")])
        step(log, "export the real-scan GD image", recon_main,
             ["export", str(out / "airsas_gd.h5"), "--mip", str(out / "airsas_gd.png")])

    total = time.perf_counter() - t_start
    (out / "SUMMARY.txt").write_text(
        f"sonarsim demo ({total:.0f} s)\n\n" + "\n".join(log))
    print(f"\ndemo finished in {total:.0f} s; pictures and SUMMARY.txt in {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
