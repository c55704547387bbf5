"""Fast-star detectability against IMBH mass and epoch baseline (generator catalogues).

NGC 3201 preset, ~2,000 luminous stars inside 17", PM errors 20-100 uas/yr for a
10-yr baseline (scaled by 10 yr / baseline), MAP no-IMBH and IMBH models of the
dynamics likelihood (King62 + cusp tied to the influence radius, core-radius prior):
the number of significant fast stars, the number expected under the IMBH model,
the expected false ones and the lower mass limit, per mass and baseline.

    python benchmarks/bench_fast_stars.py [--masses 0 500 1000 1500 3000]
        [--baselines 5 10] [--seeds 100 101 102]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import astropy.units as u
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from fast_stars_helpers import map_trial  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--masses", type=float, nargs="+", default=[0, 500, 1000, 1500, 3000])
    p.add_argument("--baselines", type=float, nargs="+", default=[5.0, 10.0])
    p.add_argument("--seeds", type=int, nargs="+", default=[100, 101, 102])
    args = p.parse_args(argv)
    print(
        "| M_BH [Msun] | baseline [yr] | fast stars per seed | expected (IMBH model) "
        "| expected false | lower limit [Msun] per seed | CPU s |"
    )
    print("|---|---|---|---|---|---|---|")
    for mass in args.masses:
        for base in args.baselines:
            t0 = time.process_time()
            n, exp1, exp0, lims = [], [], [], []
            for seed in args.seeds:
                r = map_trial(seed, mass, baseline=base)["result"]
                n.append(r.attrs["fast_n_significant"])
                exp1.append(r.attrs["fast_expected_imbh"])
                exp0.append(r.attrs["fast_expected_false"])
                lims.append(r.attrs["bh_mass_lower_limit"].to_value(u.Msun))
            cpu = (time.process_time() - t0) / len(args.seeds)
            print(
                f"| {mass:.0f} | {base:g} | {', '.join(map(str, n))} | {np.mean(exp1):.2f} "
                f"| {np.mean(exp0):.1e} | {', '.join(f'{v:.0f}' for v in lims)} | {cpu:.0f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
