"""``sonarsim import-airsas``: a real AirSAS LabVIEW CSV scan → sonar dataset (HDF5)."""
from __future__ import annotations

import argparse
from pathlib import Path

from ._options import add_box_option, parse_box

HELP = "Import a real AirSAS scan folder (LabVIEW CSVs) into a sonar dataset."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scan_dir", type=Path, help="scan folder with SysParams.csv, "
                        "Coordinates.csv, WaveformParams.csv and Flight-NNNNNN.csv")
    parser.add_argument("--background", type=Path, default=None, metavar="BG_DIR",
                        help="empty-turntable scan with the same flight numbers; subtracted "
                             "flight by flight")
    parser.add_argument("--out", type=Path, required=True, help="output dataset (.h5)")
    parser.add_argument("--pulse", default=None, metavar="lfm|commanded|lfm-5k|FILE.npy",
                        help="reference pulse: 'lfm' (default) = the LFM of WaveformParams.csv "
                             "generated at fs; 'commanded' = the column of Waveforms.csv; a "
                             "named LFM (lfm-20k, lfm-10k, lfm-5k); or a measured pulse .npy "
                             "at fs. To match the reference, which matched-filters real data "
                             "with the measured pulse (as the reference does), pass "
                             "the measured pulse .npy (the reference code's data/wfm/5khz_bw_lfm.npy) for 5 kHz scans "
                             "(airsas_20khz_measured.npy for 20 kHz)")
    parser.add_argument("--pulse-samples", type=int, default=None, metavar="N",
                        help="keep the first N samples of a .npy pulse (default 100 = 1 ms, "
                             "as the reference; 0 = all)")
    parser.add_argument("--waveform-index", type=int, default=None, metavar="I",
                        help="use only the flights of waveform I (Coordinates.csv 'Waveform' "
                             "column); required when a scan interleaves two waveforms")
    add_box_option(parser, "scene box (m) whose centre the beams point at "
                             "(default the AirSAS real box ±0.125 × ±0.125 × [0, 0.2])")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from ..errors import InputError
    from ..importers.airsas import import_airsas

    if args.pulse_samples is not None and args.pulse_samples < 0:
        raise InputError(f"--pulse-samples must be >= 0, got {args.pulse_samples}")
    ds = import_airsas(args.scan_dir, args.background, pulse=args.pulse,
                       pulse_samples=args.pulse_samples, waveform_index=args.waveform_index,
                       box=parse_box(args.box), progress=False if args.no_progress else None)
    ds.write(args.out)
    n, t = ds.waveforms.shape
    print(f"{args.out}: {n} pings x {t} samples, fs {ds.fs:g} Hz, c {ds.sound_speed:.3f} m/s, "
          f"pulse {ds.pulse.size} samples ({ds.meta['pulse_source']})")
    return 0
