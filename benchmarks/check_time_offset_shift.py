"""Clock-shift check of the time-offset estimate on a real log (issue 11 item 6).

Shifts the UWB stamps by +50, -50, +100 ms and checks that the estimated t_d
moves by the opposite amount (within 3 sd and 20 ms).  Usage::

    uwbimu import inrol ../shared/datasets/inrol_uwb_imu /tmp/inrol
    PYTHONPATH=src python benchmarks/check_time_offset_shift.py /tmp/inrol [--preset NAME]
"""

from __future__ import annotations

import argparse
import math
import time

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.io.loader import load_dataset


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--preset", default=None)
    ap.add_argument("--shifts-ms", default="0,50,-50,100")
    a = ap.parse_args()
    if a.preset:
        from uwbimu.estimation.presets import load_preset
        opts = load_preset(a.preset)
    else:
        opts = EskfOptions()
    ds0 = load_dataset(a.dataset)
    base = None
    ok_all = True
    print("shift_ms  t_d_ms  sd_ms  verdict  move_ms  expected_ms  ok")
    for s_ms in [float(v) for v in a.shifts_ms.split(",")]:
        ds = load_dataset(a.dataset)
        ds.uwb = ds0.uwb.assign(t=ds0.uwb["t"] + s_ms / 1e3)
        t0 = time.process_time()
        res = run_eskf(ds, opts)
        cpu = time.process_time() - t0
        td, sd = res.calibration["time_offset"], res.calibration["time_offset_sd"]
        if base is None:
            base = (s_ms, td, sd)
            print(f"{s_ms:8.0f} {1e3 * td:7.1f} {1e3 * sd:6.1f}  {res.calibration.get('time_offset_verdict', '-')}  "
                  f"(reference, cpu {cpu:.1f} s)")
            continue
        move = td - base[1]
        expect = -(s_ms - base[0]) / 1e3
        err = abs(move - expect)
        ok = err <= 0.020 and err <= 3 * math.hypot(sd, base[2])
        ok_all &= ok
        print(f"{s_ms:8.0f} {1e3 * td:7.1f} {1e3 * sd:6.1f}  {res.calibration.get('time_offset_verdict', '-')}  "
              f"{1e3 * move:7.1f} {1e3 * expect:8.1f}  {ok}  (cpu {cpu:.1f} s)")
    return 0 if ok_all else 1


if __name__ == "__main__":
    raise SystemExit(main())
