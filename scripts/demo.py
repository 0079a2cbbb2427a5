"""`make demo`: mesh scene -> transients -> sonar dataset -> BP, GD, NBP -> scores.

Runs the real command-line tools in order on a small problem and writes everything into one
folder, with SUMMARY.txt holding each step's command, its result lines and its time:

1. the per-bounce transients of a shipped scene (``tabletop``: a cube with a sphere on it, a
   cylinder and a dark sphere on a ground plate) over one turn, and their pictures;
2. an AirSAS-style dataset of that scene (20 kHz LFM, 20 dB total SNR) and its pictures;
3. the paper's comparison (Reed et al. 2023): coherent backprojection (BP) of the
   matched-filtered data; the pulse deconvolved (Wiener); gradient descent on complex voxels
   (GD) and neural backprojection (NBP) both fitted to the deconvolved data through the
   ellipsoidal forward model; every volume scored against the scene's mesh above the ground
   (IoU, Chamfer), one comparison figure, and a verdict computed from the scores;
4. the real AirSAS scan shipped with sonarsim (docs/data.md): its raw LabVIEW excerpt imported,
   the full scan imaged on the turntable plane with matched-filtered and deconvolved data.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from pathlib import Path

from recon.cli import main as recon_main
from sonarsim import data
from sonarsim.cli import main as sonarsim_main

# The ground truth is the scene's objects; the ground plate is not scored (docs/evaluation.md).
ABOVE_GROUND = ["--crop", "-0.2", "0.2", "-0.2", "0.2", "0.005", "0.3"]
SHAPE = ["--shape", "64", "64", "48"]
REAL_PLANE = ["--bounds", "-0.3", "0.3", "-0.3", "0.3", "0", "0", "--shape", "200", "200", "1"]
METHODS = {"bp": "BP (matched filter)", "gd": "GD (deconvolved)", "nbp": "NBP (deconvolved)"}
# NBP at demo size: the 'cpu' preset with half its rays, half its range bins per ping and a
# third of its warm start. Measured on this demo's dataset (tabletop, 720 poses; 2 shared cores):
# IoU 0.272 / Chamfer 36 mm in 33 CPU-s, against 0.305 / 33 mm in 129 CPU-s for the preset's
# sampling with 100 warm-start steps; BP 0.133 / 30 mm, GD 0.164 / 38 mm. One fit, not the
# preset's vote of three (docs/reconstruction.md "Ensemble of three fits"): a first look in
# a minute, not three.
NBP_DEMO = ["--n-rays", "300", "--bins-per-ping", "32", "--warm-start-iterations", "100",
            "--ensemble", "1"]
QUICK_SHAPE = ["--shape", "24", "24", "18"]
QUICK_NBP = ["--hash-levels", "4", "--n-rays", "100", "--bins-per-ping", "32",
             "--warm-start-iterations", "5", "--ensemble", "1"]

# Commands that refuse to replace an existing output without --force (a demo re-run
# replaces its own outputs).
REPLACES = {"render", "simulate", "import-airsas", "backproject", "gd", "nbp", "export",
            "deconvolve"}


class Demo:
    """Runs CLI steps, echoes them, and keeps each step's result lines for SUMMARY.txt."""

    def __init__(self, out: Path):
        self.out = out
        self.log: list[str] = []
        self.seconds: dict[str, float] = {}

    def step(self, title: str, tool, argv: list[str], key: str | None = None,
             summarize=None) -> str:
        """Run one CLI call (stop the demo if it fails); return what it printed on stdout.
        ``summarize(text) -> str``: what to show and log instead of the raw output."""
        if argv[0] in REPLACES:
            argv = [*argv, "--force"]
        prog = tool.__module__.split(".")[0]
        print(f"\n== {title}\n$ {prog} {' '.join(argv)}", flush=True)
        out = io.StringIO()
        t0, c0 = time.perf_counter(), time.process_time()
        with contextlib.redirect_stdout(out):
            code = tool(argv)
        seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
        text = out.getvalue()
        if code:
            print(text, end="")
            raise SystemExit(f"demo step failed ({title}), exit status {code}")
        shown = summarize(text) if summarize else text
        print(shown, end="")
        if key:
            self.seconds[key] = seconds
        shown = shown if len(shown) < 4000 else shown[:4000] + "...\n"
        self.log.append(f"## {title}  ({seconds:.1f} s wall, {cpu:.1f} s CPU)\n"
                        f"$ {prog} {' '.join(argv)}\n{shown}")
        return text

    def path(self, name: str) -> str:
        return str(self.out / name)


def score_line(text: str) -> str:
    """The headline of ``recon evaluate --json``: IoU, Chamfer, normals, which ground truth."""
    r = json.loads(text)
    best = (f" (best IoU {r['best_iou']:.3f} at {r['best_iou_threshold']:g})"
            if "best_iou" in r else "")
    return (f"IoU {r['iou']:.3f}, Chamfer {1e3 * r['chamfer_m']:.1f} mm, normal error "
            f"{r['normal_error_deg']:.0f}° at threshold {r['threshold']:g}{best}; ground truth: "
            f"{r['gt']['kind']} {Path(r['gt']['source']).name}, {r['gt']['frame']}\n")


def comparison_figure(out: Path, scores: dict, scene: str) -> Path:
    """``compare.png`` (:func:`recon.figures.comparison`, the figure of ``recon compare``):
    a ground-truth row (the scene's mesh voxelised on the reconstruction grid, and its
    render) above one row per method: top and side MIPs of |σ| above the ground on one
    colour scale, the render of its surface at the scoring threshold and its scores (the
    ``recon evaluate`` results above), the best of each starred."""
    from recon import figures

    fig = figures.comparison(
        [out / f"{key}.h5" for key in METHODS], out / "dataset.h5",
        labels=list(METHODS.values()), crop=[float(v) for v in ABOVE_GROUND[1:]],
        threshold=scores["bp"]["threshold"], results=[scores[key] for key in METHODS])
    fig.suptitle(f"{scene}: the objects above the ground, scored at threshold "
                 f"{scores['bp']['threshold']:g} (★ best)", fontsize=10)
    return figures.save(fig, out / "compare.png")


def verdict(scores: dict, seconds: dict, heights_m=None) -> str:
    """The comparison table and which method wins, from the measured scores; ``heights_m``:
    the scan's transducer heights (m), to say how much elevation aperture it had."""
    rows = [f"{'method':22s} {'IoU':>6s} {'Chamfer':>9s} {'time':>7s}"]
    for key, name in METHODS.items():
        s = scores[key]
        rows.append(f"{name:22s} {s['iou']:6.3f} {1e3 * s['chamfer_m']:6.1f} mm "
                    f"{seconds.get(key, float('nan')):6.1f} s")
    best_iou = max(METHODS, key=lambda k: scores[k]["iou"])
    best_ch = min(METHODS, key=lambda k: scores[k]["chamfer_m"])
    bp, nbp = scores["bp"], scores["nbp"]
    lines = ["", *rows, ""]
    lines.append(f"Best IoU: {METHODS[best_iou]}; best Chamfer: {METHODS[best_ch]}.")
    if best_iou == "nbp" and best_ch == "nbp":
        lines.append(
            f"NBP wins on both: IoU {nbp['iou']:.3f} vs {bp['iou']:.3f} for BP, Chamfer "
            f"{1e3 * nbp['chamfer_m']:.1f} vs {1e3 * bp['chamfer_m']:.1f} mm. Why: BP spreads each "
            "echo over its whole ellipsoid and keeps the pulse's range sidelobes, so its "
            "thresholded volume is fat and blurred; NBP first removes the pulse "
            "(deconvolution), then fits a scene whose simulated echoes match the data through "
            "the forward model; the network (hash grid + MLP) keeps the fitted scene smooth "
            "where free voxels (GD) also fit the noise.")
    else:
        lines.append(
            f"NBP does not win everything at this small size: IoU {nbp['iou']:.3f} (BP "
            f"{bp['iou']:.3f}), Chamfer {1e3 * nbp['chamfer_m']:.1f} mm (BP "
            f"{1e3 * bp['chamfer_m']:.1f} mm). The demo's scan is small and its solvers run a "
            "few hundred steps. In the paper's Table 2 (averaged over its simulated scenes) NBP "
            "leads on every metric, and on our full "
            "simulated bunny scan NBP fitted to deconvolved data scores IoU 0.69 against 0.31 "
            "for BP (docs/reconstruction.md, 'The paper's pipeline').")
    if scores["gd"]["iou"] < bp["iou"]:
        lines.append(
            "GD scores below BP: voxels are free per location, so with few pings the fit also "
            "explains noise and ellipsoid overlaps (docs/reconstruction.md); the network's "
            "smoothness is what GD lacks.")
    if heights_m is not None and len(heights_m):
        span = 1e3 * (max(heights_m) - min(heights_m))
        lines.append(
            f"Elevation aperture: {len(set(heights_m))} heights over {span:.0f} mm (the full AirSAS "
            "scan: 150 over 745 mm). Height is resolved mainly by that aperture, so with a short "
            "one every method smears the objects along z (the side views of compare.png) and "
            "both scores suffer.")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("demo_out"))
    parser.add_argument("--scene", default="tabletop", help="shipped scene name or TOML file")
    parser.add_argument("--poses", default="cylindrical:120:6",
                        help="trajectory (default: 120 angles x 6 heights = 720 poses)")
    parser.add_argument("--render-poses", default="cylindrical:120:1",
                        help="trajectory of the transients render (default: one turn of 120 "
                             "angles; 720 poses cost 69 CPU-s, 40 %% of the demo)")
    parser.add_argument("--paths-per-pose", type=int, default=4000,
                        help="paths per pose of the transients render (default 4000)")
    parser.add_argument("--mc-snr-db", type=float, default=30.0,
                        help="Monte-Carlo SNR after matched filtering of the simulated "
                             "dataset (default 30 dB, simulate's default)")
    parser.add_argument("--gd-iterations", type=int, default=300)
    parser.add_argument("--nbp-iterations", type=int, default=300)
    parser.add_argument("--quick", action="store_true",
                        help="every step at a tiny size (seconds; the test suite's run)")
    args = parser.parse_args(argv)
    shape, real_plane, nbp_options = SHAPE, REAL_PLANE, NBP_DEMO
    fidelity = ["--mc-snr-db", str(args.mc_snr_db)]
    if args.quick:
        args.poses, args.render_poses = "cylindrical:16:2", "cylindrical:16:1"
        args.paths_per_pose = 300
        args.gd_iterations = args.nbp_iterations = 5
        shape, real_plane = QUICK_SHAPE, [*REAL_PLANE[:8], "40", "40", "1"]
        nbp_options, fidelity = QUICK_NBP, ["--surface-spacing", "0.02"]
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    demo = Demo(out)
    p = demo.path
    t_start, cpu_start = time.perf_counter(), time.process_time()
    common = [args.scene, "--poses", args.poses, "--seed", "1"]

    # 1-2. transients and dataset
    demo.step("render per-bounce transients (one turn)", sonarsim_main,
              ["render", args.scene, "--poses", args.render_poses, "--seed", "1",
               "--paths-per-pose", str(args.paths_per_pose),
               "--out", p("transients.h5")])
    demo.step("pictures of the transients (one echo image per bounce, energy shares)",
              sonarsim_main, ["plot", p("transients.h5"), "--out", p("transients")])
    fidelity_text = ("20 mm surface strata" if args.quick
                     else f"Monte-Carlo SNR {args.mc_snr_db:g} dB")
    demo.step("simulate an AirSAS-style dataset (20 kHz LFM, 20 dB total SNR, "
              f"{fidelity_text})", sonarsim_main,
              ["simulate", *common, "--pulse", "lfm-20k", "--snr-db", "20", "--restart",
               *fidelity, "--out", p("dataset.h5")])
    demo.step("dataset summary", sonarsim_main, ["info", p("dataset.h5")])
    demo.step("echo images, pulse, trajectory", sonarsim_main,
              ["plot", p("dataset.h5"), "--out", p("dataset")])

    # 3. the paper's comparison
    demo.step("coherent backprojection of the matched-filtered data", recon_main,
              ["backproject", p("dataset.h5"), *shape, "--out", p("bp.h5")], key="bp")
    demo.step("pulse deconvolution (Wiener)", recon_main,
              ["deconvolve", p("dataset.h5"), "--method", "wiener", "--out", p("dataset_pd.h5")])
    demo.step("gradient descent on complex voxels, deconvolved data", recon_main,
              ["gd", p("dataset_pd.h5"), *shape, "--iterations", str(args.gd_iterations),
               "--seed", "1", "--out", p("gd.h5")], key="gd")
    demo.step("neural backprojection (hash grid + MLP), deconvolved data", recon_main,
              ["nbp", p("dataset_pd.h5"), *shape, "--iterations", str(args.nbp_iterations),
               *nbp_options, "--seed", "1", "--out", p("nbp.h5")], key="nbp")
    scores = {}
    for name in METHODS:
        extra = ["--vti", p(f"{name}.vti")] if name == "nbp" else []
        demo.step(f"export {name}: MIPs, marching-cubes mesh" + (", ParaView file" if extra else ""),
                  recon_main, ["export", p(f"{name}.h5"), "--mip", p(f"{name}_mip.png"),
                               "--mesh", p(f"{name}.ply"), *extra])
        # no threshold sweep: it costs ~13 CPU-s per volume here, and the verdict is at 0.2
        text = demo.step(f"score {name} against the scene's mesh (above the ground)", recon_main,
                         ["evaluate", p(f"{name}.h5"), "--gt", p("dataset.h5"), *ABOVE_GROUND,
                          "--no-images", "--no-sweep", "--json"], summarize=score_line)
        scores[name] = json.loads(text)
    figure = comparison_figure(out, scores, args.scene)
    demo.log.append(f"## comparison figure: ground truth, BP, GD, NBP\n{figure}\n")
    print(f"\n== comparison figure: ground truth, BP, GD, NBP\n{figure}")
    from sonarsim.dataset import SonarDataset
    heights = sorted({round(float(z), 6) for z in SonarDataset.read(p("dataset.h5")).tx[:, 2]})
    summary = verdict(scores, demo.seconds, heights)
    (out / "scores.json").write_text(json.dumps(
        {key: {"iou": scores[key]["iou"], "chamfer_m": scores[key]["chamfer_m"],
               "seconds": demo.seconds.get(key)} for key in METHODS}, indent=1))
    print(summary)
    demo.log.append("## verdict (exact protocol, threshold 0.2, above the ground)\n" + summary)

    # 4. the real scan shipped with sonarsim
    raw = data.root() / "airsas_real"
    demo.step("import the raw LabVIEW excerpt of the real scan (first 6 flights)", sonarsim_main,
              ["import-airsas", str(raw / "small_features_cutout_5k"), "--background",
               str(raw / "bg_5k"), "--out", p("airsas_excerpt.h5")])
    real = str(data.path(data.REAL_SCAN))
    demo.step("the real AirSAS scan shipped with sonarsim (360 pings, 5 kHz LFM)",
              sonarsim_main, ["info", real])
    demo.step("backproject the real scan on the turntable plane z = 0", recon_main,
              ["backproject", real, *real_plane, "--out", p("airsas_bp.h5")])
    demo.step("deconvolve the real scan (Wiener)", recon_main,
              ["deconvolve", real, "--method", "wiener", "--out", p("airsas_pd.h5")])
    demo.step("backproject the deconvolved real scan", recon_main,
              ["backproject", p("airsas_pd.h5"), *real_plane, "--out", p("airsas_bp_pd.h5")])
    for name in ("airsas_bp", "airsas_bp_pd"):
        demo.step(f"export the real-scan image {name}", recon_main,
                  ["export", p(f"{name}.h5"), "--mip", p(f"{name}.png")])

    total, cpu = time.perf_counter() - t_start, time.process_time() - cpu_start
    (out / "SUMMARY.txt").write_text(f"sonarsim demo ({total:.0f} s wall, {cpu:.0f} s CPU)\n\n"
                                     + "\n".join(demo.log))
    print(f"\ndemo finished in {total:.0f} s ({cpu:.0f} CPU-s); pictures and SUMMARY.txt in {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
