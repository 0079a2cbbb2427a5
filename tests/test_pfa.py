"""recon.pfa: polar formatting on point targets (position, resolution, 2-D scans), against a
direct sum, its far-field limit, real data, bad input and the CLI."""
from types import SimpleNamespace

import numpy as np
import pytest

from recon import pfa, straightforward, synthetic
from conftest import within_one_voxel as _within_one_voxel
from recon.grid import Grid
from sonarsim.dataset import Volume
from sonarsim.errors import InputError

CENTRE = np.array([0.0, 0.0, 0.1])
OFF = np.array([0.023, -0.017, 0.118])        # ~3.4 cm from the centre, between voxel centres
HEIGHTS = np.linspace(0.0, 0.2, 11)
C = 343.0


@pytest.fixture(scope="module")
def points_ds():
    return synthetic.point_dataset([CENTRE, OFF], [1.0, 1.0], n_pings=90, heights=HEIGHTS,
                                   sound_speed=C)


@pytest.fixture(scope="module")
def grid3d():
    # 2.5 mm voxels centred on CENTRE
    return Grid([[-0.04, 0.04], [-0.04, 0.04], [0.06, 0.14]], (33, 33, 33))


def _local_peak(mag, grid, point, radius=4):
    i = grid.index_of(point)
    sl = tuple(slice(max(a - radius, 0), a + radius + 1) for a in i)
    sub = mag[sl]
    j = np.unravel_index(np.argmax(sub), sub.shape)
    return tuple(s.start + q for s, q in zip(sl, j)), float(sub.max())


def test_point_targets_focus_within_one_voxel(points_ds, grid3d):
    vol = pfa.solve(points_ds, grid3d, progress=False)
    assert vol.method == "pfa" and vol.volume.shape == grid3d.shape
    assert vol.params["aperture_dim"] == 2
    mag = np.abs(vol.volume)
    assert _within_one_voxel(np.unravel_index(np.argmax(mag), grid3d.shape), grid3d, CENTRE)
    for p in (CENTRE, OFF):
        idx, peak = _local_peak(mag, grid3d, p)
        assert _within_one_voxel(idx, grid3d, p), (p, grid3d.position_of(idx))
    # unit scatterer at the reference point images to ~1 (scale of solve())
    assert mag[grid3d.index_of(CENTRE)] == pytest.approx(1.0, rel=0.05)


def test_nufft_equals_the_direct_sum():
    ds = synthetic.point_dataset([CENTRE, OFF], n_pings=24, heights=(0.05, 0.1, 0.15),
                                 sound_speed=C)
    g = Grid([[-0.01, 0.012], [-0.006, 0.01], [0.09, 0.11]], (12, 9, 7))  # even and odd sizes
    fast = pfa.solve(ds, g, progress=False, eps=1e-9).volume
    direct = straightforward.pfa_direct(ds, g)
    assert np.abs(fast - direct).max() < 1e-5 * np.abs(direct).max()
    # and the direct sum is not trivially small or constant
    assert np.abs(direct).max() > 0.5 and np.abs(direct).std() > 0.1


def test_range_resolution_is_c_over_2b():
    """A narrow aperture (±3°) so that the PSF along the look direction (x) is the range PSF:
    its -3 dB width must be within 15 % of c/(2B), B = 20 kHz (the 30 → 10 kHz LFM)."""
    ang = np.deg2rad(np.linspace(-3, 3, 13))
    tx = np.stack([0.85 * np.cos(ang), 0.85 * np.sin(ang), np.full_like(ang, 0.1)], axis=1)
    rx = tx * [1.015, 1.015, 1.0] + [0.0, 0.0, -0.038]
    ds = synthetic.point_dataset([CENTRE], poses=(tx, rx, -tx / 0.85), sound_speed=C)
    g = Grid([[-0.03, 0.03], [0.0, 0.0], [0.1, 0.1]], (601, 1, 1))
    m = np.abs(pfa.solve(ds, g, progress=False).volume).ravel()
    x = g.axes()[0]
    above = m >= m.max() / np.sqrt(2)
    p = int(np.argmax(m))
    lo, hi = p, p
    while lo > 0 and above[lo - 1]:
        lo -= 1
    while hi < len(m) - 1 and above[hi + 1]:
        hi += 1
    width = x[hi] - x[lo] + (x[1] - x[0])
    assert abs(x[p]) <= x[1] - x[0]
    assert width == pytest.approx(C / (2 * 20e3), rel=0.15)


def test_two_dimensional_scan_at_one_height():
    pts = np.array([[0.0, 0.0, 0.1], [0.031, 0.019, 0.1]])
    ds = synthetic.point_dataset(pts, n_pings=180, heights=(0.1,), sound_speed=C)
    g = Grid([[-0.05, 0.05], [-0.05, 0.05], [0.1, 0.1]], (41, 41, 1))
    vol = pfa.solve(ds, g, progress=False)
    assert vol.params["aperture_dim"] == 1
    mag = np.abs(vol.volume)
    for p in pts:
        idx, _ = _local_peak(mag, g, p)
        assert _within_one_voxel(idx, g, p), (p, g.position_of(idx))


def test_density_compensation_gives_the_annulus_psf():
    """A full circle at the target's height samples k-space on rings, density ∝ 1/|k|: with
    the density compensation (weights ∝ |k| per ring, equal per ping) the image of a point at
    the reference point is the 2-D Fourier transform of the band's annulus,
    PSF(r) = Σ_f W(f) J0(k r) k / Σ_f W(f) k, W = Tukey window × the matched filter's
    spectrum, k = 2πf/c·|û_TX + û_RX| (Hankel transform, closed form per frequency); measured
    to 3e-4. With the window alone (no compensation) the first sidelobe is 0.14 instead of
    0.21 (the profile off by 0.08)."""
    from scipy.special import j0
    p = np.array([0.0, 0.0, 0.1])
    ds = synthetic.point_dataset([p], n_pings=360, heights=(0.1,), sound_speed=C)
    g = Grid([[0.0, 0.04], [0.0, 0.0], [0.1, 0.1]], (81, 1, 1))
    kw = dict(reference_point=p, taper=0.25, band_db=-20.0, weights="density")
    image = pfa.solve(ds, g, progress=False, **kw).volume.ravel()
    raster = pfa.polar_samples(ds, g, **kw)
    f = raster["freqs"]
    k = 2 * np.pi * f / C * np.linalg.norm(raster["look_sum"], axis=1).mean()
    u = (f - f[0]) / (f[-1] - f[0])
    window = np.where(u < 0.125, 0.5 * (1 - np.cos(np.pi * u / 0.125)),
                      np.where(u > 0.875, 0.5 * (1 - np.cos(np.pi * (1 - u) / 0.125)), 1.0))
    w = window * raster["response"] * k
    expected = j0(np.outer(g.axes()[0], k)) @ w / w.sum()
    assert np.abs(image / image[0] - expected).max() < 0.01
    assert expected.min() < -0.2                       # the sidelobe is there to be matched


def test_far_field_defocus_grows_with_distance_from_the_reference_point():
    """The documented limit: the plane-wave approximation about x0 costs peak magnitude
    (defocus) as |x - x0| grows (AirSAS range 0.85 m). A point at the reference point
    images to ~1; one 12 cm away (same dataset, reference point moved) loses most of it."""
    p = np.array([0.0, 0.0, 0.1])
    ds = synthetic.point_dataset([p], n_pings=120, heights=HEIGHTS, sound_speed=C)
    peaks = []
    for d in (0.0, 0.04, 0.12):
        x0 = p + [d, 0.0, 0.0]
        g = Grid(np.stack([p - 0.012, p + 0.012], axis=1), (13, 13, 13))
        peaks.append(np.abs(pfa.solve(ds, g, reference_point=x0, progress=False).volume).max())
    assert peaks[0] == pytest.approx(1.0, rel=0.05)
    assert peaks[0] > peaks[1] > peaks[2]
    assert peaks[2] < 0.5


def test_real_airsas_scan_target_is_on_the_turntable(real_scan, turntable_plane):
    """PFA of the real 5 kHz AirSAS 2-D scan (the statistic of the backprojection test):
    most image energy within 0.15 m of the rotation axis, none for mislabelled time."""
    ds = real_scan
    g, X, Y, near = turntable_plane

    def frac(dataset):
        e = np.abs(pfa.solve(dataset, g, progress=False).volume[:, :, 0]) ** 2
        return e[near].sum() / e.sum()

    assert frac(ds) > 0.8
    shifted = ds.select(np.arange(ds.n_pings))
    shifted.start_sample = ds.start_sample + 150
    assert frac(shifted) < 0.6


def test_bad_input_raises_one_clear_error(points_ds, grid3d):
    with pytest.raises(InputError, match="grid"):
        pfa.solve(points_ds, [[0, 1]] * 3, progress=False)
    with pytest.raises(InputError, match="taper"):
        pfa.solve(points_ds, grid3d, taper=1.5, progress=False)
    with pytest.raises(InputError, match="band_db"):
        pfa.solve(points_ds, grid3d, band_db=3.0, progress=False)
    with pytest.raises(InputError, match="reference_point"):
        pfa.solve(points_ds, grid3d, reference_point=[0, 0], progress=False)
    with pytest.raises(InputError, match="reference point"):
        pfa.solve(points_ds, grid3d, reference_point=points_ds.tx[0], progress=False)
    bad = SimpleNamespace(**{k: getattr(points_ds, k) for k in
                             ("waveforms", "rx", "boresight", "pulse", "fs", "sound_speed",
                              "start_sample")}, tx=points_ds.tx.copy(), temperatures=None)
    bad.tx[3, 1] = np.nan
    with pytest.raises(InputError, match="pings/tx"):
        pfa.solve(bad, grid3d, progress=False)
    silent = SimpleNamespace(**{**vars(bad), "tx": points_ds.tx, "pulse": np.zeros(100)})
    with pytest.raises(InputError, match="pulse"):
        pfa.solve(silent, grid3d, progress=False)


def test_cli_round_trip_and_errors(points_ds, tmp_path, capsys):
    from recon.cli import main
    src = tmp_path / "d.h5"
    points_ds.write(src)
    out = tmp_path / "v.h5"
    rc = main(["pfa", str(src), "--bounds", "-0.04", "0.04", "-0.04", "0.04", "0.06", "0.14",
               "--shape", "17", "17", "17", "--out", str(out), "--no-progress"])
    assert rc == 0
    vol = Volume.read(out)
    g = Grid(vol.bounds, vol.shape)
    assert vol.method == "pfa" and vol.params["dataset"] == str(src)
    assert _within_one_voxel(np.unravel_index(np.argmax(np.abs(vol.volume)), g.shape), g, CENTRE)
    capsys.readouterr()
    rc = main(["pfa", str(src), "--shape", "17", "17", "17", "--taper", "2",
               "--out", str(tmp_path / "x.h5"), "--no-progress"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "taper" in err[0]
    assert not (tmp_path / "x.h5").exists()
    assert main(["pfa", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "y.h5")]) == 2


def test_sub_patches_refocus_a_point_far_from_the_grid_centre():
    """patches: each block imaged about its own centre. A point 12 cm from the centre of a
    one-block grid is defocused (peak < 0.5, the far-field limit above); with 3 blocks along
    x the block containing it is centred 1.2 cm from it and the peak is back near 1, at the
    right voxel. Every voxel lies in exactly one block."""
    p = np.array([0.12, 0.0, 0.1])
    ds = synthetic.point_dataset([p], n_pings=120, heights=HEIGHTS, sound_speed=C)
    g = Grid(np.array([[-0.16, 0.16], [-0.012, 0.012], [0.088, 0.112]]), (81, 7, 7))
    one = np.abs(pfa.solve(ds, g, progress=False).volume)
    three = pfa.solve(ds, g, progress=False, patches=(3, 1, 1))
    mag = np.abs(three.volume)
    assert one.max() < 0.5
    assert mag.max() == pytest.approx(1.0, rel=0.1)
    assert _within_one_voxel(np.unravel_index(np.argmax(mag), mag.shape), g, p)
    blocks = pfa.patch_grids(g, 3)
    cover = np.zeros(g.shape, int)
    for index, _ in blocks:
        cover[index] += 1
    assert len(blocks) == 27 and np.all(cover == 1)
    with pytest.raises(InputError, match="patches"):
        pfa.solve(ds, g, progress=False, patches=2, reference_point=p)


def test_uniform_weights_about_the_point_equal_backprojection():
    """weights='uniform' sums every polar sample alike, as backprojection sums every ping's
    matched-filtered sample: with no taper, the whole band and the reference point at the
    target, PFA and backprojection (an independent time-domain implementation) give the same
    normalised image of a point to 1 % of its peak, on a 3-D cylindrical scan; the default
    density weights (|k|^D) differ from it by far more (sharper in range), so the agreement
    is not a property of any PSF."""
    from recon import backprojection
    p = np.array([0.012, -0.009, 0.108])
    ds = synthetic.point_dataset([p], n_pings=72, heights=HEIGHTS, sound_speed=C)
    g = Grid(np.stack([p - 0.02, p + 0.02], axis=1), (17, 17, 17))
    bp = np.abs(backprojection.solve(ds, g, progress=False).volume)
    kw = dict(reference_point=p, taper=0.0, band_db=-60.0, progress=False)
    uniform = np.abs(pfa.solve(ds, g, weights="uniform", **kw).volume)
    density = np.abs(pfa.solve(ds, g, weights="density", **kw).volume)
    assert pfa.solve(ds, g, weights="uniform", **kw).params["weights"] == "uniform"
    bp, uniform, density = (v / v.max() for v in (bp, uniform, density))
    assert np.abs(uniform - bp).max() < 0.01
    assert np.abs(density - bp).max() > 0.05


def test_unknown_weights_are_refused(points_ds, grid3d):
    with pytest.raises(InputError, match="weights"):
        pfa.solve(points_ds, grid3d, weights="ramp", progress=False)
