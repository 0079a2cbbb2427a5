"""Benchmark: transient rendering throughput of the ``sonar_transient`` wavefront integrator.

Scene: the bunny mesh shipped with sonarsim (``sonarsim.data``) (metres, standing on z = 0) on a 0.4 × 0.4 m diffuse ground.
Poses: an evenly spread subset of the reference cylindrical scan (360 angles × 150 heights),
reference crop window (14 360 bins of c/(fs·20)), cone beams of 30°.

Three ways of doing the same job are timed:
  wavefront      sonarsim.render.iter_render: all poses of a chunk × all paths in one kernel
  per-pose       the same integrator, one kernel launch per pose (a Python loop)
  numpy+mitsuba  a straightforward implementation: a Python loop over poses, NumPy for
                 sampling/shading/binning, Mitsuba only to trace the rays of each bounce

Run:  .venv/bin/python benchmarks/bench_render.py [--poses 2000] [--paths 10000] [--bounces 3]
(the TX-cone tracer, bounce1='cone'), or

      .venv/bin/python benchmarks/bench_render.py --estimators [--estimator-poses 40]

to compare the bounce-1 surface estimator (default) with the TX-cone tracer: per-pose wall
and CPU time, facets/s or paths/s, and the Monte-Carlo SNR after matched filtering
(lfm-20k pulse) measured from two half-estimates, 10·log10((E_total − E_mc)/E_mc) with
E_mc = Σ|MF((h₀ − h₁)/2)|² — for all bounces and for bounce 1 alone, or

      .venv/bin/python benchmarks/bench_render.py --per-path [--compare-paths 1e4,1e5,1e6]
          [--mitransient-python /tmp/mitr/bin/python] [--rounds 3]

for the TX-cone tracer's cost per path (paths/s, median of interleaved rounds), its profile
at the largest path count (trace kernel, lane ordering, other kernels, Python/launch and
read-back; and the same trace with the lanes in index order, i.e. without the coherent
ordering), and, given a Python in which ``mitransient`` is importable (never a dependency
of this project: e.g. ``python3 -m venv /tmp/mitr; /tmp/mitr/bin/pip install mitransient``),
the same job in mitransient's ``transient_path`` integrator, side by side: the bunny
scene, the same poses, the same path-length window, ``max_depth`` = bounces + 1 and no
Russian roulette, a spot light at the TX (cutoff = half the TX beamwidth) and a 1×1-pixel
perspective camera at the RX (field of view = the RX beamwidth; a square instead of a
cone), spp = paths per pose, one ``render`` per pose (its pose update included).
The machine may be shared: timings are noisy; CPU seconds (all threads) are printed next
to wall seconds: CPU/2 is what an idle 2-core machine would take.
"""
from __future__ import annotations

import argparse
import math
import resource
import sys
import time
from pathlib import Path

import numpy as np

from sonarsim import data

ROOT = Path(__file__).resolve().parents[1]
MESH = data.path("bunny.obj")
FULL_SCAN_POSES = 54_000
TARGET_SECONDS, TARGET_GB = 90.0, 2.0


def bunny_scene(mi, mesh: Path):
    diffuse = {"type": "diffuse", "reflectance": {"type": "spectrum", "value": 1.0}}
    return mi.load_dict({
        "type": "scene",
        "bunny": {"type": "obj", "filename": str(mesh), "bsdf": diffuse},
        "ground": {"type": "rectangle", "bsdf": diffuse,
                   "to_world": mi.ScalarTransform4f().scale([0.2, 0.2, 1.0])},
    })


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20   # Linux: KiB


def _basis(b: np.ndarray):
    """Two unit vectors orthogonal to unit ``b`` [3]."""
    helper = np.array([1.0, 0, 0]) if abs(b[0]) < 0.9 else np.array([0, 1.0, 0])
    s = np.cross(b, helper)
    s /= np.linalg.norm(s)
    return s, np.cross(b, s)


def numpy_pose(mi, scene, tx, rx, b_tx, b_rx, window, paths, bounces, rng, half_angle):
    """One pose, straightforwardly: NumPy everywhere except Mitsuba's ray queries."""
    cos_cut = math.cos(half_angle)
    cos_t = 1 - rng.random(paths) * (1 - cos_cut)
    sin_t, phi = np.sqrt(1 - cos_t ** 2), 2 * np.pi * rng.random(paths)
    s, t = _basis(b_tx)
    dirs = (np.outer(sin_t * np.cos(phi), s) + np.outer(sin_t * np.sin(phi), t)
            + np.outer(cos_t, b_tx))
    origins = np.tile(tx, (paths, 1))
    throughput = np.full(paths, 2 * np.pi * (1 - cos_cut) / paths)
    length = np.zeros(paths)
    hist = np.zeros((bounces, window.n_bins))
    rays = 0
    for bounce in range(bounces):
        rays += int(np.count_nonzero(throughput))
        ray = mi.Ray3f(mi.Point3f(*origins.T.astype(np.float32)),
                       mi.Vector3f(*dirs.T.astype(np.float32)))
        si = scene.ray_intersect(ray)
        hit = si.is_valid().numpy()
        albedo = si.bsdf(ray).eval_diffuse_reflectance(si).numpy().reshape(-1)
        p, n, dist_t = si.p.numpy().T, si.n.numpy().T, si.t.numpy()
        rx_points = mi.Point3f(*np.tile(rx, (len(origins), 1)).T.astype(np.float32))  # no literals
        shadow = scene.ray_test(si.spawn_ray_to(rx_points))
        blocked = shadow.numpy()
        keep = hit & (throughput > 0)
        rays += int(np.count_nonzero(keep))
        n = np.where((np.einsum("ij,ij->i", n, dirs) > 0)[:, None], -n, n)
        length = length + np.where(keep, dist_t, 0)
        to_rx = rx - p
        r = np.linalg.norm(to_rx, axis=1)
        w_rx = to_rx / r[:, None]
        cos_o = np.einsum("ij,ij->i", n, w_rx)
        in_rx_beam = (-w_rx @ b_rx) >= cos_cut
        value = throughput * albedo / np.pi * np.maximum(cos_o, 0) / r ** 2
        ok = keep & ~blocked & (cos_o > 0) & in_rx_beam
        u = (length + r - window.path_start) / window.bin_width - 0.5
        j0 = np.floor(u[ok]).astype(np.int64)
        f = u[ok] - j0
        for j, w in ((j0, 1 - f), (j0 + 1, f)):
            inside = (j >= 0) & (j < window.n_bins)
            np.add.at(hist[bounce], j[inside], (value[ok] * w)[inside])
        if bounce + 1 == bounces:
            break
        # Continue with cosine-weighted directions. Dead paths stay (with zero weight and
        # a harmless ray) so every bounce has the same array sizes: Dr.Jit then reuses its
        # compiled kernels from pose to pose.
        p = np.where(keep[:, None], p, 0.0)
        n = np.where(keep[:, None], n, [0, 0, 1.0])
        length, throughput = np.where(keep, length, 0.0), np.where(keep, throughput * albedo, 0.0)
        u1, u2 = rng.random(paths), rng.random(paths)
        rad, ang = np.sqrt(u1), 2 * np.pi * u2
        helper = np.where((np.abs(n[:, 0]) < 0.9)[:, None], [1.0, 0, 0], [0, 1.0, 0])
        s = np.cross(n, helper)
        s /= np.linalg.norm(s, axis=1, keepdims=True)
        t = np.cross(n, s)
        dirs = ((rad * np.cos(ang))[:, None] * s + (rad * np.sin(ang))[:, None] * t
                + np.sqrt(np.maximum(0.0, 1 - u1))[:, None] * n)
        origins = p + 1e-5 * n
    return hist.astype(np.float32), rays


def mc_snr_db(halves: np.ndarray, crop, bounce_index=None) -> float:
    """MC SNR after matched filtering of half-estimates [2, n, B, T] (see the module doc)."""
    from sonarsim.fidelity import mf_energy
    from sonarsim.signals import AIRSAS_FS, pulse_from_spec
    from sonarsim.simulate import oversampled_pulse, transients_to_waveforms
    pulse = pulse_from_spec("lfm-20k", AIRSAS_FS).samples
    pulse_os = oversampled_pulse(pulse, 20)
    wf = transients_to_waveforms(halves.mean(axis=0), pulse_os, 20, crop.num_samples,
                                 bounce_index)
    d = transients_to_waveforms((halves[0] - halves[1]) / 2, pulse_os, 20, crop.num_samples,
                                bounce_index)
    total, noise = mf_energy(wf, pulse).sum(), mf_energy(d, pulse).sum()
    return 10 * math.log10(max(total - noise, 1e-300) / noise)


def estimators(args, mi, scene, all_poses, window) -> int:
    """Surface estimator vs TX-cone tracer: cost per pose and MC SNR after matched filtering."""
    from sonarsim import geometry, render
    from sonarsim.signals import AIRSAS_FS
    crop = geometry.crop_window(all_poses, geometry.SIM_BOX, render.DEFAULT_SOUND_SPEED, AIRSAS_FS)
    pick = np.linspace(0, len(all_poses) - 1, args.estimator_poses).round().astype(int)
    poses = all_poses[pick]
    configs = [("surface", {"bounce1": "surface"}, 1, args.bounces),
               ("surface", {"bounce1": "surface"}, 1, 1),
               ("cone", {"bounce1": "cone"}, args.paths, args.bounces),
               ("cone", {"bounce1": "cone"}, args.paths, 1)]
    print(f"\nEstimators: {len(poses)} poses spread over the scan, halves=True (both halves "
          f"timed), lfm-20k pulse\n{'estimator':<10} {'B':>2} {'samples/pose':>13} "
          f"{'wall ms/pose':>13} {'CPU ms/pose':>12} {'samples/s (CPU)':>16} {'MC SNR dB':>10} "
          f"{'bounce 1 dB':>12} {'scan (CPU/2)':>13}")
    for name, props, paths, bounces in configs:
        integ = mi.load_dict({"type": "sonar_transient", "max_bounces": bounces, **props})
        p = poses[:2]
        integ.render_transients(scene, p.tx, p.rx, p.tx_boresight, p.rx_boresight,
                                window.path_start, window.bin_width, window.n_bins,
                                max(2, paths), 0, halves=True)     # compile, build the facets
        if name == "surface":
            samples = integ.surface_strata(scene)[0].count * 2
        else:
            samples = paths
        out, wall, cpu = [], time.perf_counter(), time.process_time()
        for a in range(0, len(poses), 20):
            p = poses[a:a + 20]
            out.append(integ.render_transients(
                scene, p.tx, p.rx, p.tx_boresight, p.rx_boresight, window.path_start,
                window.bin_width, window.n_bins, max(2, paths), 0, pose_offset=a, halves=True))
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        h = np.concatenate(out, axis=1)
        snr = mc_snr_db(h, crop)
        snr1 = mc_snr_db(h, crop, [0])
        n = len(poses)
        print(f"{name:<10} {bounces:>2} {samples:>13,} {wall / n * 1e3:>13.1f} "
              f"{cpu / n * 1e3:>12.1f} {samples * n / cpu:>16.3g} {snr:>10.1f} {snr1:>12.1f} "
              f"{FULL_SCAN_POSES * cpu / n / 2 / 60:>10.1f} min", flush=True)
    print("samples: facets x 2 halves (surface) or paths (cone) per pose; scan: the "
          f"{FULL_SCAN_POSES}-pose scan's render time at CPU/2 (an idle 2-core machine)")
    return 0


# ------------------------------------------------------------------------ per-path cost
def _median(xs):
    return float(np.median(np.asarray(xs, float)))


def mitransient_worker(job_file: str) -> int:
    """Run in a Python with mitransient: render poses of the job on request (one line
    'POSE SPP' per request on stdin; one JSON line per answer on stdout)."""
    import json
    import os

    import drjit as dr
    import mitsuba as mi
    mi.set_variant("llvm_ad_mono")
    import mitransient
    job = np.load(job_file)
    diffuse = {"type": "diffuse", "reflectance": {"type": "spectrum", "value": 1.0}}

    def look(origin, direction):
        up = [0.0, 0.0, 1.0] if abs(direction[2]) < 0.99 * np.linalg.norm(direction) else [1.0, 0, 0]
        return mi.ScalarTransform4f().look_at(origin=[float(v) for v in origin],
                                              target=[float(v) for v in origin + direction],
                                              up=up)

    half_tx = float(job["tx_beamwidth"]) / 2
    scene = mi.load_dict({
        "type": "scene",
        "bunny": {"type": "obj", "filename": str(job["mesh"]), "bsdf": diffuse},
        "ground": {"type": "rectangle", "bsdf": diffuse,
                   "to_world": mi.ScalarTransform4f().scale([0.2, 0.2, 1.0])},
        "integrator": {"type": "transient_path", "max_depth": int(job["bounces"]) + 1,
                       "rr_depth": int(job["bounces"]) + 100},
        "light": {"type": "spot", "cutoff_angle": half_tx, "beam_width": half_tx,
                  "intensity": {"type": "spectrum", "value": 1.0},
                  "to_world": look(job["tx"][0], job["tx_dir"][0])},
        "sensor": {"type": "perspective", "fov": float(job["rx_beamwidth"]),
                   "to_world": look(job["rx"][0], job["rx_dir"][0]),
                   "film": {"type": "transient_hdr_film", "width": 1, "height": 1,
                            "temporal_bins": int(job["n_bins"]),
                            "start_opl": float(job["path_start"]),
                            "bin_width_opl": float(job["bin_width"]),
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}}})
    params = mi.traverse(scene)
    integrator = scene.integrator()
    print(json.dumps({"ready": True, "version": getattr(mitransient, "__version__", "?"),
                      "mitsuba": mi.__version__, "threads": dr.thread_count(),
                      "pid": os.getpid()}), flush=True)
    for line in sys.stdin:
        i, spp = (int(v) for v in line.split())
        t0 = time.perf_counter()
        params["light.to_world"] = look(job["tx"][i], job["tx_dir"][i])
        params["sensor.to_world"] = look(job["rx"][i], job["rx_dir"][i])
        params.update()
        _, transient = integrator.render(scene, spp=spp, seed=i)
        energy = float(np.asarray(transient, np.float64).sum())
        print(json.dumps({"seconds": time.perf_counter() - t0, "energy": energy}), flush=True)
    return 0


class _Mitransient:
    """A mitransient worker process (see :func:`mitransient_worker`)."""

    def __init__(self, python: str, poses, window, bounces: int, mesh: Path, workdir: Path):
        import json
        import subprocess
        job = workdir / "mitransient_job.npz"
        np.savez(job, tx=poses.tx, rx=poses.rx, tx_dir=poses.tx_boresight,
                 rx_dir=poses.rx_boresight, n_bins=window.n_bins, path_start=window.path_start,
                 bin_width=window.bin_width, bounces=bounces, mesh=str(mesh),
                 tx_beamwidth=30.0, rx_beamwidth=30.0)
        self.proc = subprocess.Popen([python, str(Path(__file__).resolve()),
                                      "--mitransient-worker", str(job)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self._json = json
        self.info = self._answer()

    def _answer(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the mitransient worker stopped (see its error above)")
        return self._json.loads(line)

    def render(self, pose: int, spp: int) -> tuple[float, float]:
        self.proc.stdin.write(f"{pose} {spp}\n")
        self.proc.stdin.flush()
        a = self._answer()
        return a["seconds"], a["energy"]

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


def per_path(args, mi, scene, all_poses, window) -> int:
    """The TX-cone tracer's cost per path at several path counts, side by side with
    mitransient when a Python with it is given; profile at the largest count."""
    import tempfile

    import drjit as dr

    from sonarsim import render
    st = sys.modules["sonarsim.plugins.sonar_transient"]
    tracer = sys.modules["sonarsim.plugins._cone_tracer"]
    counts = sorted({int(float(v)) for v in args.compare_paths.split(",")})
    total_paths = max(counts) * 4                     # paths per measurement and method
    integ = render.make_integrator(args.bounces, bounce1="cone")
    workdir = Path(tempfile.mkdtemp(prefix="bench_render_"))
    mitr = None
    if args.mitransient_python:
        mitr = _Mitransient(args.mitransient_python, all_poses, window, args.bounces,
                            args.mesh, workdir)
        print(f"mitransient {mitr.info['version']} (mitsuba {mitr.info['mitsuba']}, "
              f"{mitr.info['threads']} threads) in {args.mitransient_python}")

    def ours(p, paths, offset=0):
        dr.sync_thread()
        t0 = time.perf_counter()
        h = integ.render_transients(scene, p.tx, p.rx, p.tx_boresight, p.rx_boresight,
                                    window.path_start, window.bin_width, window.n_bins,
                                    paths, 0, pose_offset=offset)
        return time.perf_counter() - t0, float(h.sum(dtype=np.float64))

    print(f"\nPer-path cost, TX-cone tracer (bounce1='cone'), {args.bounces} bounces, bunny + "
          f"ground, {window.n_bins} bins; sonarsim renders a chunk of poses per launch, "
          f"mitransient one pose per render(); medians of {args.rounds} interleaved rounds")
    print(f"{'paths/pose':>10} {'poses':>6} {'sonarsim paths/s':>17} {'mitransient':>12} "
          f"{'ratio':>6} {'numpy':>10} {'ratio':>6} {'s/pose ours':>12} {'s/pose mitr':>12} "
          f"{'energy/pose ours':>17} {'mitr':>9}")
    rng = np.random.default_rng(0)
    p0 = all_poses[0]                                 # compile the NumPy baseline's kernels
    numpy_pose(mi, scene, p0.tx[0], p0.rx[0], p0.tx_boresight[0], p0.rx_boresight[0], window,
               100, args.bounces, rng, math.radians(15.0))
    rows = []
    for paths in counts:
        k = max(2, min(400, total_paths // paths))
        pick = np.linspace(0, len(all_poses) - 1, k).round().astype(int)
        poses = all_poses[pick]
        ours(poses[:2], paths)                        # compile / warm up
        if mitr:
            mitr.render(int(pick[0]), paths)
        t_ours, t_mitr, e_ours, e_mitr = [], [], 0.0, 0.0
        for _ in range(args.rounds):
            t, e_ours = ours(poses, paths)
            t_ours.append(t)
            if mitr:
                answers = [mitr.render(int(i), paths) for i in pick]
                t_mitr.append(sum(a[0] for a in answers))
                e_mitr = sum(a[1] for a in answers)
        rate = k * paths / _median(t_ours)
        rate_m = k * paths / _median(t_mitr) if mitr else float("nan")
        t0 = time.perf_counter()                      # the NumPy baseline, on one pose
        numpy_pose(mi, scene, poses.tx[0], poses.rx[0], poses.tx_boresight[0],
                   poses.rx_boresight[0], window, paths, args.bounces, rng,
                   math.radians(15.0))
        rate_np = paths / (time.perf_counter() - t0)
        rows.append((paths, rate, rate_m))
        print(f"{paths:>10,} {k:>6} {rate:>17.3e} {rate_m:>12.3e} {rate / rate_m:>6.2f} "
              f"{rate_np:>10.3e} {rate / rate_np:>6.0f} {_median(t_ours) / k:>12.4f} "
              f"{(_median(t_mitr) / k if mitr else float('nan')):>12.4f} "
              f"{e_ours / k:>17.4e} {(e_mitr / k if mitr else float('nan')):>9.3e}", flush=True)
    if mitr:
        mitr.close()
        print("energy/pose: sonarsim reports ∫ b_R L dω over its 30° RX cone (0.21 sr); "
              "mitransient's pixel the mean radiance over its 30° square field of view "
              "(≈ ∫ L dω / 0.27 sr): a check of magnitude, not a comparison")

    # Profile at the largest count: kernels (trace, ordering, other) vs Python and read-back.
    paths = max(counts)
    poses = all_poses[np.linspace(0, len(all_poses) - 1, 4).round().astype(int)]
    timer = {"order": 0.0}
    original = st.SonarTransientIntegrator._coherent_order

    def timed(self, *a, **kw):
        dr.sync_thread()
        t0 = time.perf_counter()
        out = original(self, *a, **kw)
        dr.sync_thread()
        timer["order"] += time.perf_counter() - t0
        return out

    st.SonarTransientIntegrator._coherent_order = timed
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    profile, plain = [], []
    try:
        for _ in range(args.rounds):
            timer["order"] = 0.0
            dr.kernel_history()
            wall, _ = ours(poses, paths)
            kernels = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
            times = sorted(k["execution_time"] / 1e3 for k in kernels)
            profile.append((wall, times[-1], sum(times), timer["order"]))
            keep = tracer._ORDER_MIN_PATHS
            tracer._ORDER_MIN_PATHS = 2**40                  # lanes in index order
            try:
                plain.append(ours(poses, paths)[0])
            finally:
                tracer._ORDER_MIN_PATHS = keep
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        st.SonarTransientIntegrator._coherent_order = original
    wall, trace, kernels, order = (np.median([p[i] for p in profile]) for i in range(4))
    n = len(poses) * paths
    print(f"\nProfile: {len(poses)} poses x {paths:,} paths, {args.bounces} bounces (medians):")
    print(f"  wall {wall:.3f} s = {n / wall:.3e} paths/s; trace kernel (one fused launch per "
          f"batch of <= 2^24 lanes: ray casts, shading, splats) {trace:.3f} s "
          f"({trace / wall:.0%}), lane ordering {order:.3f} s ({order / wall:.0%}), all "
          f"kernels {kernels:.3f} s; Python, launches and read-back "
          f"{max(0.0, wall - kernels):.3f} s ({max(0.0, wall - kernels) / wall:.0%})")
    print(f"  lanes in index order (no coherent ordering): {_median(plain):.3f} s = "
          f"{n / _median(plain):.3e} paths/s -> ordering gains "
          f"{_median(plain) / wall:.2f}x")
    print(f"peak RSS of this process: {peak_rss_gb():.2f} GB (numpy: the straightforward "
          f"NumPy + Mitsuba implementation above, one pose; ratio = sonarsim / numpy)")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--estimators", action="store_true",
                    help="compare the surface estimator with the TX-cone tracer (see above)")
    ap.add_argument("--estimator-poses", type=int, default=40)
    ap.add_argument("--poses", type=int, default=2000)
    ap.add_argument("--paths", type=int, default=10_000)
    ap.add_argument("--bounces", type=int, default=3)
    ap.add_argument("--baseline-poses", type=int, default=3)
    ap.add_argument("--mesh", type=Path, default=MESH)
    ap.add_argument("--per-path", action="store_true",
                    help="cost per path of the TX-cone tracer (and mitransient's, see below)")
    ap.add_argument("--compare-paths", default="1e4,1e5,1e6",
                    help="paths per pose for --per-path, comma-separated")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds (--per-path)")
    ap.add_argument("--mitransient-python", default=None, metavar="PYTHON",
                    help="a Python in which mitransient is importable: time it on the same job")
    ap.add_argument("--mitransient-worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.mitransient_worker:
        return mitransient_worker(args.mitransient_worker)
    if not args.mesh.is_file():
        print(f"mesh not found: {args.mesh}", file=sys.stderr)
        return 2

    from sonarsim import geometry, render, runtime
    mi = runtime.mitsuba()
    import drjit as dr

    scene = bunny_scene(mi, args.mesh)
    all_poses = geometry.trajectory("cylindrical")
    pick = np.linspace(0, len(all_poses) - 1, args.poses).round().astype(int)
    poses = all_poses[pick]
    window = render.path_window(scene, all_poses, box=geometry.SIM_BOX)
    if args.estimators:
        return estimators(args, mi, scene, all_poses, window)
    if args.per_path:
        return per_path(args, mi, scene, all_poses, window)
    chunk = render.choose_chunk_size(args.paths, args.bounces, window.n_bins)
    n_tri = sum(s.face_count() for s in scene.shapes() if isinstance(s, mi.Mesh))
    print(f"scene: bunny {n_tri} triangles + ground; window {window.n_bins} bins of "
          f"{window.bin_width * 1e3:.4f} mm from {window.path_start:.4f} m; "
          f"{args.poses} of {len(all_poses)} poses x {args.paths} paths x {args.bounces} bounces; "
          f"chunk {chunk} poses")

    # Compile (or load from Dr.Jit's disk cache) before timing.
    t0 = time.perf_counter()
    integ = render.make_integrator(args.bounces, bounce1="cone")
    p = poses[:2]
    integ.render_transients(scene, p.tx, p.rx, p.tx_boresight, p.rx_boresight,
                            window.path_start, window.bin_width, window.n_bins, 100, 0)
    warmup = time.perf_counter() - t0

    # Rays per path, from an instrumented run on a few poses.
    stats: dict = {}
    p = poses[:: max(1, args.poses // 20)]
    integ.render_transients(scene, p.tx, p.rx, p.tx_boresight, p.rx_boresight,
                            window.path_start, window.bin_width, window.n_bins, args.paths, 0,
                            ray_stats=stats)
    rays_per_path = (stats["intersect"] + stats["shadow"]) / (len(p) * args.paths)

    rows = []
    dr.sync_thread()
    t0 = time.perf_counter()
    energy = np.zeros(args.bounces)
    chunk_times, t_prev = [], t0
    for sl, hist in render.iter_render(scene, poses, paths_per_pose=args.paths,
                                       bounces=args.bounces, window=window, progress=False,
                                       bounce1="cone"):
        energy += hist.sum(axis=(0, 2), dtype=np.float64)
        now = time.perf_counter()
        chunk_times.append((sl.stop - sl.start, now - t_prev))
        t_prev = now
    dr.sync_thread()
    wave_s = time.perf_counter() - t0
    wave_rss = peak_rss_gb()
    rows.append(("wavefront (chunks)", args.poses, args.paths, wave_s))

    k = min(args.poses, max(1, 10 * args.baseline_poses))
    t0 = time.perf_counter()
    for i in range(k):
        p = poses[i]
        integ.render_transients(scene, p.tx, p.rx, p.tx_boresight, p.rx_boresight,
                                window.path_start, window.bin_width, window.n_bins,
                                args.paths, 0, pose_offset=i)
    rows.append(("per-pose launches", k, args.paths, time.perf_counter() - t0))

    rng = np.random.default_rng(0)
    p = poses[0]        # warm-up: compile the baseline's Mitsuba kernels
    numpy_pose(mi, scene, p.tx[0], p.rx[0], p.tx_boresight[0], p.rx_boresight[0],
               window, 100, args.bounces, rng, math.radians(15.0))
    t0 = time.perf_counter()
    np_rays = 0
    for i in range(args.baseline_poses):
        p = poses[i]
        _, r = numpy_pose(mi, scene, p.tx[0], p.rx[0], p.tx_boresight[0], p.rx_boresight[0],
                          window, args.paths, args.bounces, rng, math.radians(15.0))
        np_rays += r
    rows.append(("numpy+mitsuba/pose", args.baseline_poses, args.paths, time.perf_counter() - t0))

    print(f"\n{'method':<20} {'poses':>6} {'paths/s':>12} {'rays/s':>12} {'s/pose':>10} "
          f"{'full scan':>11} {'speed-up':>9}")
    base_rate = rows[-1][1] * rows[-1][2] / rows[-1][3]
    for name, n, paths, secs in rows:
        rate = n * paths / secs
        full = FULL_SCAN_POSES * paths / rate
        print(f"{name:<20} {n:>6} {rate:>12.3e} {rate * rays_per_path:>12.3e} {secs / n:>10.4f} "
              f"{full:>10.0f}s {rate / base_rate:>8.1f}x")
    full_scan = FULL_SCAN_POSES * args.paths / (args.poses * args.paths / wave_s)
    print("\nwavefront chunks (poses, seconds): "
          + ", ".join(f"({n}, {t:.2f})" for n, t in chunk_times)
          + "  [the first chunk also pays first-touch page faults of its buffers]")
    if len(chunk_times) > 1:
        steady = sum(t for _, t in chunk_times[1:]) / sum(n for n, _ in chunk_times[1:])
        print(f"steady-state: {args.paths / steady:.3e} paths/s -> full scan "
              f"{FULL_SCAN_POSES * steady:.0f} s")
    print(f"\nrays per path (intersections + shadow rays): {rays_per_path:.2f} "
          f"(numpy baseline, on its {args.baseline_poses} poses: "
          f"{np_rays / (args.baseline_poses * args.paths):.2f})")
    print(f"compile/warm-up: {warmup:.2f} s; mean energy per pose by bounce: "
          f"{', '.join(f'{e / args.poses:.3e}' for e in energy)}")
    print(f"peak RSS during the wavefront render: {wave_rss:.2f} GB (target <= {TARGET_GB} GB)")
    print(f"projected full scan ({FULL_SCAN_POSES} poses x {args.paths} paths): {full_scan:.0f} s "
          f"(target <= {TARGET_SECONDS:.0f} s) -> "
          f"{'OK' if full_scan <= TARGET_SECONDS and wave_rss <= TARGET_GB else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
