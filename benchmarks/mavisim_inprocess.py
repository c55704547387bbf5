"""In-process timing of the published MAVISIM package (run by ``bench_render.py``).

Runs inside MAVISIM's own environment (``python mavisim_inprocess.py FIELD PSFS
[--npy OUT]``), never imports mavispm, and does what ``python -m mavisim FIELD
PSFS`` does (MAVISIM 1.1.20 ``__main__.main``: read the source list, build an
``ImageGenerator`` of 12,000 x 12,000 pixels of 3.75 mas, render every star,
bin 2 x 2 and crop to 30") except writing the FITS file. Prints one JSON line:
the CPU time (user + sys of this process, all threads) and the wall time of the
set-up (PSF FFTs), the star loop and the binning, after the imports.
"""

from __future__ import annotations

import argparse
import json
import resource
import time


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("field")
    ap.add_argument("psfs")
    ap.add_argument("--npy", help="save the 4000 x 4000 image here (numpy .npy)")
    args = ap.parse_args()
    import numpy as np
    from mavisim.__main__ import read_source
    from mavisim.generate_image import ImageGenerator

    c0, w0 = cpu(), time.perf_counter()
    source = read_source(args.field)
    source.trim()
    imgen = ImageGenerator(12_000, source, psfs_file=args.psfs, which_psf=None)
    c1 = cpu()
    imgen.main()
    c2 = cpu()
    im = imgen.get_rebinned_cropped(2, 30)
    c3, w3 = cpu(), time.perf_counter()
    if args.npy:
        np.save(args.npy, im)
    out = {
        "stars": int(source.flux.shape[0]),
        "setup_cpu": c1 - c0,
        "stars_cpu": c2 - c1,
        "bin_cpu": c3 - c2,
        "total_cpu": c3 - c0,
        "total_wall": w3 - w0,
        "shape": list(im.shape),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
