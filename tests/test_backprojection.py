"""recon.backprojection: focusing, conventions, options, real data, CLI."""
import numpy as np
import pytest

from recon import backprojection as bp
from recon import straightforward, synthetic
from conftest import within_one_voxel as _within_one_voxel
from recon.grid import Grid
from sonarsim import signals
from sonarsim.dataset import SonarDataset, Volume
from sonarsim.errors import InputError

POINT = np.array([0.013, -0.021, 0.094])
HEIGHTS = np.linspace(0.0, 0.25, 6)


@pytest.fixture(scope="module")
def point_ds():
    return synthetic.point_dataset([POINT], n_pings=30, heights=HEIGHTS)


@pytest.fixture(scope="module")
def grid3d():
    # 2.5 mm voxels, the point is between voxel centres.
    return Grid([[-0.04, 0.04], [-0.05, 0.03], [0.06, 0.14]], (33, 33, 33))


def _peak(vol, grid):
    return np.unravel_index(np.argmax(np.abs(vol)), grid.shape)


def test_point_scatterer_focuses_within_one_voxel(point_ds, grid3d):
    vol = bp.solve(point_ds, grid3d, progress=False)
    assert isinstance(vol, Volume) and vol.volume.shape == grid3d.shape
    assert vol.method == "backprojection" and vol.params["upsample"] == 5
    assert _within_one_voxel(_peak(vol.volume, grid3d), grid3d, POINT)
    # Coherent focus: the peak is far above the typical voxel.
    mag = np.abs(vol.volume)
    assert mag.max() > 8 * np.median(mag)


def test_matches_numpy_reference_implementation(point_ds):
    g = Grid([[-0.03, 0.03], [-0.03, 0.03], [0.08, 0.11]], (9, 8, 3))
    a = bp.backproject(point_ds, g, upsample=3, progress=False)
    b = straightforward.backproject_numpy(point_ds, g, upsample=3)
    np.testing.assert_allclose(a, b, atol=2e-5 * np.abs(b).max())


@pytest.fixture(scope="module")
def temperature_ds():
    """Two point scatterers, 40 pings on 5 heights, per-ping temperatures (5 °C / 35 °C)."""
    pulse = signals.named_pulse("lfm-20k", 100e3)
    tx, rx, bore = synthetic.circular_poses(8, heights=np.linspace(0.0, 0.2, 5))
    temps = np.where(np.arange(len(tx)) % 2 == 0, 5.0, 35.0)
    speeds = signals.sound_speed_air(temps)
    n_t, start = 420, 380
    pts = [POINT, POINT + [0.03, 0.01, -0.02]]
    w = np.zeros((len(tx), n_t), np.float32)
    for c in np.unique(speeds):
        sel = speeds == c
        w[sel] = synthetic.point_echoes(pts, 1.0, tx[sel], rx[sel], pulse, 100e3, c, n_t, start)
    return SonarDataset(waveforms=w, tx=tx, rx=rx, boresight=bore, pulse=pulse, fs=100e3,
                        sound_speed=float(speeds.mean()), source="test", start_sample=start,
                        temperatures=temps)


# Grid dims that are not multiples of the 4x4x4 lane bricks (partial bricks on every axis).
FUSED_GRID = Grid([[-0.03, 0.06], [-0.05, 0.02], [0.05, 0.11]], (9, 7, 6))


@pytest.mark.parametrize("loop,mask,incoherent,mode", [
    ("unrolled", None, False, "linear"), ("unrolled", 3.0, True, "linear"),
    ("symbolic", None, True, "linear"), ("symbolic", 3.0, False, "linear"),
    ("unrolled", 3.0, False, "nearest"), ("symbolic", None, False, "floor")])
def test_fused_kernel_matches_float64_numpy(temperature_ds, loop, mask, incoherent, mode):
    """Both loop forms of the fused kernel against the independent float64 NumPy
    backprojector: several pings, per-ping sound speed, beam mask on/off, coherent and
    incoherent, every interpolation rule. Tolerance: float32 round-off of the delay (~1e-4
    upsampled samples, i.e. ~4e-5 of the signal per ping at 15 samples per carrier cycle); a
    delay error of 0.1 sample would give ~4e-2."""
    kw = dict(upsample=3, interpolation=mode, incoherent=incoherent, tx_beam_mask=mask)
    a = bp.backproject(temperature_ds, FUSED_GRID, progress=False, loop=loop, **kw)
    b = straightforward.backproject_numpy(temperature_ds, FUSED_GRID, **kw)
    scale = np.abs(b).max()
    assert scale > 0
    err = np.abs(a - b)
    if mode == "linear":
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-4 * scale)
    else:
        # 'floor'/'nearest' are discontinuous: a delay within round-off of a rounding edge
        # may pick the neighbouring sample in one implementation (one ping's sample step).
        buf = bp.upsampled_signals(temperature_ds, np.arange(temperature_ds.n_pings), 3, incoherent)
        step = np.abs(buf[..., 2] + 1j * buf[..., 3]).max()       # |s[k+1] - s[k]|
        assert np.mean(err <= 1e-4 * scale) > 0.98
        assert err.max() <= 2 * step + 1e-4 * scale
    if mask is not None:     # the mask really removes contributions in this case
        full = straightforward.backproject_numpy(temperature_ds, FUSED_GRID, **{**kw, "tx_beam_mask": None})
        assert np.abs(full - b).max() > 0.1 * scale


def _straightforward_float32(ds, grid, upsample, mask, incoherent):
    """The pre-fusion float32 form, ping by ping: |v - t| by subtraction, the tent read of
    recon.straightforward.tent_gather_jit from the (s[k], s[k+1]) buffer, the beam test on v - t."""
    import drjit as dr
    from recon import interp
    from recon._jit import jit
    m = jit()
    c = bp.ping_constants(ds, upsample, True, mask)
    s = bp.upsampled_signals(ds, np.arange(ds.n_pings), upsample, incoherent)
    n_up = s.shape[1]
    buf = m.Float(straightforward.packed_buffer(s[..., 0] + 1j * s[..., 1]).ravel())
    pts = grid.points().astype(np.float32)
    vx, vy, vz = (m.Float(pts[:, i]) for i in range(3))
    are, aim = dr.zeros(m.Float, len(pts)), dr.zeros(m.Float, len(pts))
    for i, q in enumerate(c):
        dx, dy, dz = vx - float(q[0]), vy - float(q[1]), vz - float(q[2])
        d1 = dr.sqrt(dx * dx + dy * dy + dz * dz)
        d2 = dr.sqrt((vx - float(q[3])) ** 2 + (vy - float(q[4])) ** 2 + (vz - float(q[5])) ** 2)
        u = (d1 + d2) * float(q[6]) + float(q[7])
        active = dx * float(q[8]) + dy * float(q[9]) + dz * float(q[10]) >= float(q[11]) * d1
        re, im = straightforward.tent_gather_jit(m, buf, m.UInt32(i * n_up), u, n_up, "linear", active)
        are, aim = are + re, aim + im
        dr.eval(are, aim)
    return (np.asarray(are) + 1j * np.asarray(aim)).reshape(grid.shape)


@pytest.mark.parametrize("mask,incoherent", [(None, False), (3.0, True)])
def test_fused_kernel_matches_the_straightforward_float32_form(temperature_ds, mask, incoherent):
    """Same results as the plain float32 delay-and-sum (the kernel before the expanded
    distances, the difference buffer and the packet gather) within float32 round-off:
    6e-5 of the peak (each float32 form is within ~2e-5 of float64 here; a delay error of
    0.1 upsampled sample would give ~4e-2)."""
    a = bp.backproject(temperature_ds, FUSED_GRID, upsample=3, tx_beam_mask=mask,
                       incoherent=incoherent, progress=False)
    b = _straightforward_float32(temperature_ds, FUSED_GRID, 3, mask, incoherent)
    np.testing.assert_allclose(a, b, rtol=0, atol=6e-5 * np.abs(b).max())


def test_brick_lane_order_gives_bit_identical_volumes(temperature_ds):
    """The lane order changes nothing per voxel: bricks and plain C order agree exactly."""
    for loop in ("unrolled", "symbolic"):
        a = bp.backproject(temperature_ds, FUSED_GRID, progress=False, loop=loop, tx_beam_mask=3.0)
        b = bp.backproject(temperature_ds, FUSED_GRID, progress=False, loop=loop, tx_beam_mask=3.0,
                           brick=None)
        np.testing.assert_array_equal(a, b)


def test_cpu_kernel_reads_the_signal_with_packet_gathers(temperature_ds):
    """The kernel reads both tent nodes with one 16-byte packet gather per voxel-ping, also
    from a NumPy block that is not 64-byte aligned (Dr.Jit would otherwise fall back to four
    per-float gathers: half the speed on the CPU). Checked in the IR of the launched kernels."""
    import drjit as dr
    from recon._jit import jit
    if bp._backend_is_cuda(jit()):
        pytest.skip("LLVM IR check")
    n_up = temperature_ds.waveforms.shape[1] * 3
    host = bp.upsampled_signals(temperature_ds, np.arange(temperature_ds.n_pings), 3, False)
    raw = np.empty(host.size + 4, np.float32)
    start = 4 - (raw.ctypes.data // 4) % 4 if (raw.ctypes.data // 4) % 16 == 0 else 0
    unaligned = raw[start:start + host.size].reshape(host.shape)
    unaligned[...] = host
    assert unaligned.ctypes.data % 64 != 0
    consts = bp.ping_constants(temperature_ds, 3)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()                                    # clear
        a = bp.delay_and_sum(iter([unaligned]), consts, FUSED_GRID, n_up, loop="unrolled")
        irs = [k["ir"].getvalue() for k in dr.kernel_history() if k.get("ir") is not None]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    kernels = [ir for ir in irs if "gather" in ir]
    assert kernels and all("gather_4xf32" in ir and "masked.gather" not in ir for ir in kernels)
    np.testing.assert_array_equal(a, bp.delay_and_sum(iter([host]), consts, FUSED_GRID, n_up))


def test_brick_order_is_a_permutation_of_bricks():
    order = bp.brick_order((9, 7, 6))
    assert np.array_equal(np.sort(order), np.arange(9 * 7 * 6))
    ix, iy, iz = np.unravel_index(bp.brick_order((8, 8, 8)), (8, 8, 8))
    # Every run of 64 lanes is one 4x4x4 brick.
    for k in range(0, 512, 64):
        assert {(x // 4, y // 4, z // 4) for x, y, z in zip(ix[k:k + 64], iy[k:k + 64], iz[k:k + 64])} \
            == {(ix[k] // 4, iy[k] // 4, iz[k] // 4)}
    assert np.array_equal(bp.brick_order((3, 2, 5), None), np.arange(30))


def test_start_sample_is_honoured(point_ds):
    # The same echoes recorded in a window that starts 37 samples later focus identically.
    later = synthetic.point_dataset([POINT], n_pings=30, heights=HEIGHTS,
                                    start_sample=point_ds.start_sample + 37,
                                    n_samples=point_ds.waveforms.shape[1] - 37)
    g = Grid([[-0.03, 0.03], [-0.03, 0.03], [0.094, 0.094]], (25, 25, 1))
    a = bp.backproject(point_ds, g, progress=False)
    b = bp.backproject(later, g, progress=False)
    assert _peak(a, g) == _peak(b, g)
    np.testing.assert_allclose(np.abs(b).max(), np.abs(a).max(), rtol=0.02)


def test_interpolation_modes_and_truncation_bias(point_ds):
    g = Grid([[-0.02, 0.04], [-0.05, 0.01], [0.094, 0.094]], (25, 25, 1))
    # Reference: a finely upsampled signal, where interpolation details no longer matter.
    ref = bp.backproject(point_ds, g, upsample=40, progress=False)
    err = {}
    for mode in bp.INTERPOLATIONS:
        v = bp.backproject(point_ds, g, interpolation=mode, progress=False)
        assert _within_one_voxel(_peak(v, g), g, POINT)
        err[mode] = np.linalg.norm(v - ref) / np.linalg.norm(ref)
    # Linear interpolation at R = 5 is closer to the fine reference than the reference's
    # truncation to the lower sample (a half-sample bias) and than rounding.
    assert err["linear"] < err["nearest"] < err["floor"]
    assert err["linear"] < 0.05


def test_incoherent_is_real_nonnegative_and_peaks_at_point(point_ds, grid3d):
    v = bp.backproject(point_ds, grid3d, incoherent=True, progress=False)
    assert np.all(v.imag == 0) and np.all(v.real >= 0)
    assert _within_one_voxel(_peak(v, grid3d), grid3d, POINT)


def test_tx_beam_mask_zeroes_exactly_the_voxels_outside_every_cone(point_ds):
    # Every voxel's delay is inside the recorded window, so only the mask can zero it.
    # Two pings only: every point of the plane lies on some boresight line of a full orbit.
    two = point_ds.select([0, 37])
    g = Grid([[-0.12, 0.12], [-0.12, 0.12], [0.1, 0.1]], (31, 31, 1))
    width = 6.0
    v = bp.backproject(two, g, tx_beam_mask=width, progress=False)
    pts = g.points()
    inside_any = np.zeros(len(pts), bool)
    for tx, b in zip(two.tx, two.boresight):
        d = pts - tx
        cosang = d @ b / np.linalg.norm(d, axis=1)
        inside_any |= cosang >= np.cos(np.radians(width / 2)) + 1e-5
    outside_all = np.ones(len(pts), bool)
    for tx, b in zip(two.tx, two.boresight):
        d = pts - tx
        outside_all &= d @ b / np.linalg.norm(d, axis=1) < np.cos(np.radians(width / 2)) - 1e-5
    flat = np.abs(v).ravel()
    assert np.all(flat[outside_all] == 0)
    assert np.mean(flat[inside_any] > 0) > 0.99
    assert outside_all.any() and inside_any.any()


def test_per_ping_sound_speed_from_temperatures():
    pulse = signals.named_pulse("lfm-20k", 100e3)
    tx, rx, bore = synthetic.circular_poses(24, heights=HEIGHTS[::2])
    temps = np.where(np.arange(len(tx)) % 2 == 0, 5.0, 35.0)
    speeds = signals.sound_speed_air(temps)
    n_t, start = 500, 350
    w = np.zeros((len(tx), n_t), np.float32)
    for c in np.unique(speeds):
        sel = speeds == c
        w[sel] = synthetic.point_echoes([POINT], 1.0, tx[sel], rx[sel], pulse, 100e3, c, n_t, start)
    ds = SonarDataset(waveforms=w, tx=tx, rx=rx, boresight=bore, pulse=pulse, fs=100e3,
                      sound_speed=float(speeds.mean()), source="test", start_sample=start,
                      temperatures=temps)
    g = Grid([[-0.03, 0.05], [-0.06, 0.02], [0.094, 0.094]], (33, 33, 1))
    per_ping = bp.backproject(ds, g, progress=False)
    mean_c = bp.backproject(ds, g, per_ping_sound_speed=False, progress=False)
    assert _within_one_voxel(_peak(per_ping, g), g, POINT)
    # A 9 % sound-speed error per ping defocuses the mean-speed image.
    assert np.abs(per_ping).max() > 1.5 * np.abs(mean_c).max()


def test_bad_options_and_empty_dataset_raise_input_error(point_ds, grid3d):
    with pytest.raises(InputError):
        bp.solve(point_ds, grid3d, upsample=0, progress=False)
    with pytest.raises(InputError):
        bp.solve(point_ds, grid3d, interpolation="cubic", progress=False)
    with pytest.raises(InputError):
        bp.solve(point_ds, grid3d, tx_beam_mask=-3, progress=False)
    with pytest.raises(InputError):
        bp.solve(point_ds, np.zeros((3, 2)), progress=False)
    with pytest.raises(InputError):
        empty = SonarDataset(waveforms=np.zeros((0, 100), np.float32), tx=np.zeros((0, 3)),
                             rx=np.zeros((0, 3)), boresight=np.zeros((0, 3)),
                             pulse=point_ds.pulse, fs=100e3, sound_speed=343.0, source="test")
        bp.solve(empty, grid3d, progress=False)


def test_real_airsas_scan_target_is_on_the_turntable(real_scan, turntable_plane):
    """BP of the real 5 kHz AirSAS scan at z = 0 over ±0.3 m.

    The cut-out target stands on the turntable, centred on the rotation axis. Statistic:
    the fraction of image energy |v|² within 0.15 m of the axis (19 % of the area). A
    focused image concentrates it there (> 0.9) with its energy centroid near the axis;
    the control — the same data with the time axis mislabelled by 150 samples (0.52 m of
    round-trip path, 0.26 m of range) — spreads it into a ring and fails the same statistic.
    """
    ds = real_scan
    g, X, Y, near = turntable_plane

    def stats(dataset):
        e = np.abs(bp.backproject(dataset, g, progress=False)[:, :, 0]) ** 2
        centroid = np.array([(e * X).sum(), (e * Y).sum()]) / e.sum()
        return e[near].sum() / e.sum(), centroid

    frac, centroid = stats(ds)
    assert frac > 0.9
    assert np.linalg.norm(centroid) < 0.03
    shifted = ds.select(np.arange(ds.n_pings))
    shifted.start_sample = ds.start_sample + 150
    frac_bad, _ = stats(shifted)
    assert frac_bad < 0.6


def test_cli_round_trip_and_errors(point_ds, tmp_path, capsys):
    from recon.cli import main
    src = tmp_path / "d.h5"
    point_ds.write(src)
    out = tmp_path / "v.h5"
    rc = main(["backproject", str(src), "--bounds", "-0.04", "0.04", "-0.05", "0.03", "0.06", "0.14",
               "--shape", "17", "17", "17", "--out", str(out), "--no-progress"])
    assert rc == 0
    vol = Volume.read(out)
    g = Grid(vol.bounds, vol.shape)
    assert vol.method == "backprojection" and vol.shape == (17, 17, 17)
    assert _within_one_voxel(_peak(vol.volume, g), g, POINT)
    rc = main(["backproject", str(src), "--shape", "17", "0", "17", "--out", str(tmp_path / "x.h5"),
               "--incoherent", "--beam-mask", "30", "--upsample", "2", "--no-progress"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shape" in err[0]
    assert not (tmp_path / "x.h5").exists()
    rc = main(["backproject", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "y.h5")])
    assert rc == 2
