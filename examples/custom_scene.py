"""A scene of your own, its per-bounce transients, and what each bounce contributes.

Writes a TOML scene (the shipped Stanford bunny fitted into the scene box, a 3 cm sphere beside
it, the ground), loads it, renders the per-bounce path-length histograms (transients) of a
circular scan and writes their pictures (``sonarsim.plot_transients``): one echo image per
bounce, each bounce's share of the energy, profiles of a few pings.

    python examples/custom_scene.py --out custom_scene/          # 360 poses, ~1 min on 2 cores
    python examples/custom_scene.py --quick --out /tmp/x          # 12 poses, seconds (the tests)

Files: ``scene.toml``, ``transients.h5`` (docs/formats.md), ``pictures/*.png|exr``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from sonarsim import geometry
from sonarsim.plot_transients import energy_per_bounce, plot_transients
from sonarsim.render import render_to_file
from sonarsim.runtime import mitsuba
from sonarsim.scene import load_scene

SCENE = """\
# A custom scene: the reference's bunny (shipped with sonarsim) and a small sphere.
[ground]                       # a 0.4 m x 0.4 m Lambertian plate at z = 0
albedo = 1.0

[[object]]
mesh = "bunny.obj"             # no such file here: the mesh shipped with sonarsim
fit = true                     # scale into the rig's scene box, standing on the ground
fit_fill = 0.5

[[object]]
shape = "sphere"
radius = 0.03
center = [0.13, 0.0, 0.03]     # metres; resting on the ground beside the bunny
"""


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("custom_scene"))
    parser.add_argument("--quick", action="store_true", help="a tiny run (the test suite's)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    scene_file = args.out / "scene.toml"
    scene_file.write_text(SCENE)
    spec = load_scene(scene_file)
    lo, hi = spec.gt_mesh().bounds
    print(f"scene: {len(spec.objects)} objects, {len(spec.gt_mesh().faces)} triangles, "
          f"extent {lo.round(3).tolist()} .. {hi.round(3).tolist()} m")

    # 30 angles x 12 heights of the AirSAS rig (12 poses for --quick); three bounces.
    poses = geometry.trajectory("cylindrical:6:2" if args.quick else "cylindrical:30:12")
    mitsuba()                                           # Dr.Jit + plugins, once per process
    # Bounce 1 and the later bounces are integrated over surface facets of about
    # `surface_spacing` metres (docs/transient_rendering.md); 8 mm is the integrator's default.
    path, shape, window = render_to_file(
        spec.to_mitsuba(), poses, args.out / "transients.h5", bounces=3, seed=1,
        surface_spacing=0.025 if args.quick else 0.008, progress=not args.quick)
    print(f"transients: {shape[0]} poses x {shape[1]} bounces x {shape[2]} bins of "
          f"{window.bin_width * 1e3:.3f} mm path length")

    from sonarsim.dataset import Transients
    tr = Transients.read(path)
    written = plot_transients(tr, args.out / "pictures")
    energy = energy_per_bounce(tr)
    shares = 100 * energy / energy.sum()
    for b, share in enumerate(shares, start=1):
        print(f"bounce {b}: {share:5.2f} % of the received energy")
    print(f"pictures: {', '.join(p.name for p in written if p.suffix == '.png')}")
    return {"transients": tr, "shares": shares, "pictures": written, "spec": spec}


if __name__ == "__main__":
    main()
