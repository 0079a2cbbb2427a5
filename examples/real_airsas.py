"""A real AirSAS scan, imaged: the shipped 2-D circular scan of a flat cut-out target.

The scan (360 pings at one height, 5 kHz-bandwidth LFM, background subtracted; docs/data.md)
is backprojected coherently on the turntable plane z = 0, once with the matched-filtered data and
once with the Wiener-deconvolved data, and the two images are drawn side by side in dB. A 2-D
circular scan has no elevation resolution, so an image of the plane is what it supports. The
raw LabVIEW files of its first flights are shipped too: ``import_airsas`` reads them (the
importer the dataset was made with).

    python examples/real_airsas.py --out real_airsas/          # 401 x 401 pixels, seconds
    python examples/real_airsas.py --quick --out /tmp/x         # 101 x 101 (the test suite's)

Files: ``bp_matched.h5``, ``bp_deconvolved.h5`` (volumes, docs/formats.md), ``real_airsas.png``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from recon import backprojection, deconvolution
from recon.grid import Grid
from sonarsim import data
from sonarsim.figures import save_figure, to_db
from sonarsim.importers.airsas import import_airsas

HALF_WIDTH = 0.3        # metres of the turntable imaged on each side of the rotation axis


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("real_airsas"))
    parser.add_argument("--quick", action="store_true", help="a small image (the test suite's)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    scan = data.real_scan()                          # a SonarDataset: 360 pings x 1000 samples
    print(f"real scan: {scan.n_pings} pings, fs {scan.fs / 1e3:g} kHz, c {scan.sound_speed:.1f} m/s "
          f"from {scan.temperatures.mean():.2f} °C")
    raw = import_airsas(data.root() / "airsas_real/small_features_cutout_5k",
                        data.root() / "airsas_real/bg_5k", progress=False)
    print(f"raw excerpt: {raw.n_pings} flights imported from LabVIEW CSV; equal to the shipped "
          f"dataset's first pings: {np.allclose(raw.waveforms, scan.waveforms[:raw.n_pings], atol=1e-8)}")

    n = 101 if args.quick else 401
    plane = Grid([[-HALF_WIDTH, HALF_WIDTH], [-HALF_WIDTH, HALF_WIDTH], [0.0, 0.0]], (n, n, 1))
    images = {"matched filter": backprojection.solve(scan, plane),
              "Wiener-deconvolved": backprojection.solve(deconvolution.deconvolve(scan, "wiener"),
                                                         plane)}
    images["matched filter"].write(args.out / "bp_matched.h5")
    images["Wiener-deconvolved"].write(args.out / "bp_deconvolved.h5")

    from matplotlib.figure import Figure
    fig = Figure(figsize=(11, 5), layout="constrained")
    axs = fig.subplots(1, 2)
    edge = HALF_WIDTH + HALF_WIDTH / (n - 1)
    for ax, (name, vol) in zip(axs, images.items()):
        mag = np.abs(vol.volume[:, :, 0]).T                       # rows y, columns x
        im = ax.imshow(to_db(mag, 40.0), origin="lower", cmap="inferno", vmin=-40, vmax=0,
                       extent=(-edge, edge, -edge, edge))
        ax.set_title(f"backprojection, {name} data", fontsize=10)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    fig.colorbar(im, ax=list(axs), label="|image| [dB re max]", shrink=0.85)
    fig.suptitle("real AirSAS scan of a flat cut-out target on the turntable (z = 0), 5 kHz LFM")
    figure = save_figure(fig, args.out / "real_airsas.png")
    print(f"figure: {figure}")
    return {"scan": scan, "images": images, "figure": figure, "raw": raw}


if __name__ == "__main__":
    main()
