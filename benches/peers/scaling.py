#!/usr/bin/env python3
"""How ctrecon's kernels grow with size and threads: the `ctrecon recon` CLI (whole process: read the
`.npy`, reconstruct, write the `.npy`) on the exact projections of the modified Shepp-Logan phantom, for a
sweep of sizes, on 1 and on 2 threads (`RAYON_NUM_THREADS`), under `/usr/bin/time` for the wall time and
the peak resident memory; then the iterative methods and marching cubes (`ctrecon mesh`) at one size each,
on 1 and on 2 threads.

Sizes: parallel FBP on n² pixels from 1.5625·n views of ceil(1.42·n) detectors (views grow with n, so the
work grows as n³); FDK on n³ voxels from 360 views of (2n)² detector pixels (work n³·360, input 360·4n²).
Printed: a Markdown table with seconds, the speed-up of 2 threads over 1, the growth exponent of the time
against the previous size (log t₂/t₁ ÷ log n₂/n₁), voxel updates per second per thread, and the peak memory
against the input plus the output. `--quick` stops at FBP 1024² and FDK 256³ and runs the second table at
small sizes. Not run by CI.

Usage: benches/peers/scaling.py [--quick] [--bin target/release/ctrecon] [--work DIR]
"""

import argparse
import json
import math
import os
import subprocess
import sys
import time

from common import cone_case, loadavg, parallel_case, timed

HERE = os.path.dirname(os.path.abspath(__file__))


def timed_on(cmd, threads):
    """(seconds, peak RSS bytes) of `cmd` on `threads` rayon threads."""
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    env.pop("RUST_BACKTRACE", None)
    return timed(cmd, env)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--bin", default=os.path.join(HERE, "..", "..", "target", "release", "ctrecon"))
    ap.add_argument("--work", default=os.path.join(HERE, "work"))
    args = ap.parse_args()
    os.makedirs(args.work, exist_ok=True)
    fbp = [256, 512, 1024] + ([] if args.quick else [2048])
    fdk = [64, 128, 256] + ([] if args.quick else [512])
    cases = []
    for n in fbp:
        views, det = round(1.5625 * n), math.ceil(1.42 * n) | 1
        geo = parallel_case(n, views, det)["geometry"]
        cases.append(("FBP", n, geo, "fbp", views * n * n, 4 * views * det, 4 * n * n))
    for n in fdk:
        det, pitch = 2 * n, 1.5 / 2
        geo = {"type": "cone", "angles": {"count": 360}, "dso_mm": 4.0 * n, "dsd_mm": 6.0 * n,
               "detector": {"nu": det, "nv": det, "du_mm": pitch, "dv_mm": pitch, "offset_u_mm": 0,
                            "offset_v_mm": 0}}
        cases.append(("FDK", n, geo, "fdk", 360 * n ** 3, 4 * 360 * det * det, 4 * n ** 3))
    print("# %s, %d CPUs, load average %s at start, %s" % (
        time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), os.cpu_count(), loadavg(), args.bin))
    print("| kernel | size | 1 thread s | 2 threads s | speed-up | growth exponent (2 threads) "
          "| updates/s per thread (1 / 2 threads) | peak RSS MB (2 threads) | input + output MB | load |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    prev = {}
    for kind, n, geo, algorithm, updates, in_bytes, out_bytes in cases:
        cmd, out = recon_command(args, "%s_%d" % (kind.lower(), n), n, geo, algorithm, {})
        load = loadavg()
        t1, _ = timed_on(cmd, 1)
        t2, rss = timed_on(cmd, 2)
        growth = ""
        if kind in prev:
            n0, t0 = prev[kind]
            growth = "%.2f" % (math.log(t2 / t0) / math.log(n / n0))
        prev[kind] = (n, t2)
        print("| %s | %d%s | %.3f | %.3f | %.2f× | %s | %.2g / %.2g | %.0f | %.1f | %s |" % (
            kind, n, "²" if kind == "FBP" else "³", t1, t2, t1 / t2, growth, updates / t1,
            updates / t2 / 2, rss / 1e6, (in_bytes + out_bytes) / 1e6, load), flush=True)
        os.remove(out)
    per_kernel(args)
    return 0


def per_kernel(args):
    """The iterative methods (parallel 256² from 360 views; cone beam 128³ from 360 × 256², two iterations)
    and marching cubes (the rasterised 3D phantom at 0.5, 256³), each on 1 and 2 threads."""
    par, cone, mesh_n = (128, 180, 183), (48, 90, 72), 128
    if not args.quick:
        par, cone, mesh_n = (256, 360, 363), (128, 360, 256), 256
    n, views, det = par
    pgeo = parallel_case(*par)["geometry"]
    n3 = cone[0]
    cgeo = cone_case(*cone)["geometry"]
    runs = [("SIRT x10", "%d² / %d" % (n, views), n, pgeo, "sirt", 10),
            ("SART x10", "%d² / %d" % (n, views), n, pgeo, "sart", 10),
            ("CGLS x50", "%d² / %d" % (n, views), n, pgeo, "cgls", 50),
            ("cone SIRT x2", "%d³ / %d × %d²" % cone, n3, cgeo, "sirt", 2),
            ("cone CGLS x2", "%d³ / %d × %d²" % cone, n3, cgeo, "cgls", 2)]
    print()
    print("| kernel | size | 1 thread s | 2 threads s | speed-up | peak RSS MB (2 threads) | load |")
    print("|---|---|---|---|---|---|---|")
    for kind, size, m, geo, algorithm, iterations in runs:
        cmd, out = recon_command(args, "%s_%s_%d" % (algorithm, geo["type"], m), m, geo, algorithm,
                                 {"iterations": iterations})
        row(kind, size, cmd)
        os.remove(out)
    ref = os.path.join(args.work, "phantom3_%d.npy" % mesh_n)
    if not os.path.exists(ref):
        subprocess.run([args.bin, "phantom", "--dims", "3", "--size", str(mesh_n), "--fov-mm", str(mesh_n),
                        "--supersample", "2", "--out", ref], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
    stl = os.path.join(args.work, "scaling_mesh.stl")
    row("marching cubes", "%d³, iso 0.5" % mesh_n,
        [args.bin, "mesh", "--input", ref, "--iso", "0.5", "--all-components", "--out", stl])
    os.remove(stl)


def recon_command(args, tag, n, geo, algorithm, params):
    """The `ctrecon recon` command for an n-pixel (or voxel) side reconstruction of the phantom's exact
    projections in geometry `geo` (written under `args.work` as `tag`, once), and its output path."""
    gpath, data = os.path.join(args.work, tag + ".json"), os.path.join(args.work, tag + ".npy")
    out = os.path.join(args.work, tag + "_out.npy")
    with open(gpath, "w") as f:
        json.dump(geo, f)
    if not os.path.exists(data):
        subprocess.run([args.bin, "phantom", "--geometry", gpath, "--fov-mm", str(n), "--out", data],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    cmd = [args.bin, "recon", "--input", data, "--geometry", gpath, "--algorithm", algorithm,
           "--params", json.dumps(params), "--size", str(n), "--pixel-mm", "1", "--max-bytes",
           str(16 << 30), "--output", out]
    return cmd, out


def row(kind, size, cmd):
    load = loadavg()
    t1, _ = timed_on(cmd, 1)
    t2, rss = timed_on(cmd, 2)
    print("| %s | %s | %.3f | %.3f | %.2f× | %.0f | %s |" % (kind, size, t1, t2, t1 / t2, rss / 1e6, load),
          flush=True)


if __name__ == "__main__":
    sys.exit(main())
