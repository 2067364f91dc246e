#!/usr/bin/env python3
"""CGLS iteration by iteration: ctrecon, ASTRA, and CGLS written out in numpy over ASTRA's own projector.

On exact but discretisation-inconsistent data (the analytic Shepp-Logan projections of `peers.py`), CGLS
semi-converges: the error against the phantom falls to a minimum and then grows as the iterations fit the
model error. "RMSE at equal iterations" past that minimum then rewards the solver that converges more
slowly. This script prints, for every iteration count up to `--iterations`, the RMSE against the phantom
and the data residual |A x - b| (A = ASTRA's `linear` projector for every image, one yardstick) of:

- `ctrecon`: the `ctrecon recon` CLI with `{"iterations": k}` (dot products accumulated in f64);
- `ASTRA`: ASTRA's CPU CGLS, run one iteration at a time;
- `numpy f64`: CGLS in numpy over ASTRA's projector, dot products in f64 (the exact method);
- `numpy f32 seq`: the same with every dot product summed in f32, one term after the other, as ASTRA's
  `CglsAlgorithm.cpp` accumulates them.

Then per program the smallest RMSE along the path and where it falls, and the RMSE of ctrecon at the first
iteration whose residual is at most ASTRA's at `--at` iterations (equal fit to the data).

Run: `benches/peers/run.sh --cgls-paths [--quick] [--iterations N] [--at K]` (installs the pinned peers,
builds ctrecon). Takes about two minutes at the default size.
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np

from common import parallel_case
from peers import HERE, angles, case_files, ctrecon_bin, rmse


def astra_operator(case, shape):
    import astra

    n = case["n"]
    vg = astra.create_vol_geom(n, n)
    pg = astra.create_proj_geom("parallel", 1.0, shape[1], -angles(case))
    pid = astra.create_projector("linear", pg, vg)
    return astra, vg, pg, pid, astra.OpTomo(pid)


def numpy_cgls(op, b, n, iterations, f32_sequential):
    """CGLS from zero over `op`; the images after each iteration."""

    def dot(u, v):
        if f32_sequential:
            return float(np.cumsum((u.astype(np.float32) * v.astype(np.float32)).ravel(), dtype=np.float32)[-1])
        return float(np.sum(u * v))

    def fwd(x):
        return (op * x.ravel().astype(np.float32)).reshape(b.shape).astype(np.float64)

    def back(y):
        return (op.T * y.ravel().astype(np.float32)).reshape(n, n).astype(np.float64)

    x, r = np.zeros((n, n)), b.copy()
    z = back(r)
    p, gamma = z.copy(), dot(z, z)
    images = []
    for _ in range(iterations):
        w = fwd(p)
        alpha = gamma / dot(w, w)
        x += alpha * p
        r -= alpha * w
        z = back(r)
        gamma_new = dot(z, z)
        p = z + (gamma_new / gamma) * p
        gamma = gamma_new
        images.append(x.copy())
    return images


def astra_cgls(astra, vg, pg, pid, data, iterations):
    sid = astra.data2d.create("-sino", pg, data)
    rid = astra.data2d.create("-vol", vg, 0)
    cfg = astra.astra_dict("CGLS")
    cfg.update(ProjectorId=pid, ProjectionDataId=sid, ReconstructionDataId=rid)
    alg = astra.algorithm.create(cfg)
    images = []
    for _ in range(iterations):
        astra.algorithm.run(alg, 1)  # continues where the previous call stopped
        images.append(astra.data2d.get(rid).copy())
    astra.algorithm.delete(alg)
    astra.data2d.delete(rid)
    astra.data2d.delete(sid)
    return images


def ctrecon_cgls(data_path, geo, grid, out, iterations):
    images = []
    for k in range(1, iterations + 1):
        subprocess.run([ctrecon_bin(), "recon", "--input", data_path, "--geometry", geo, "--algorithm", "cgls",
                        "--params", json.dumps({"iterations": k}), "--grid", grid, "--output", out],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        images.append(np.load(out))
    return images


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="128² from 180 views instead of 256² from 360")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--at", type=int, default=50, help="ASTRA's iteration count for the equal-fit comparison")
    ap.add_argument("--work", default=os.path.join(HERE, "work"), help="folder for the .npy files")
    args = ap.parse_args()
    if not 1 <= args.at <= args.iterations:
        ap.error("--at must lie in 1..--iterations")
    os.makedirs(args.work, exist_ok=True)
    case = parallel_case(128, 180, 183) if args.quick else parallel_case(256, 360, 363)
    n = case["n"]
    data_path, _, geo, grid, out, data, ref = case_files(case, "cgls", args.work)
    astra, vg, pg, pid, op = astra_operator(case, data.shape)
    b = data.astype(np.float64)

    def residual(img):
        return float(np.linalg.norm((op * np.asarray(img, np.float32).ravel()).astype(np.float64) - b.ravel()))

    paths = {
        "ctrecon": ctrecon_cgls(data_path, geo, grid, out, args.iterations),
        "ASTRA": astra_cgls(astra, vg, pg, pid, data, args.iterations),
        "numpy f64": numpy_cgls(op, b, n, args.iterations, False),
        "numpy f32 seq": numpy_cgls(op, b, n, args.iterations, True),
    }
    stats = {name: [(rmse(img, ref), residual(img)) for img in imgs] for name, imgs in paths.items()}
    names = list(stats)
    print("# CGLS on %d² from %d parallel views, exact projections; RMSE against the phantom, residual |Ax - b|"
          " with ASTRA's linear projector" % (n, case["geometry"]["angles"]["count"]))
    print("| iterations | " + " | ".join("%s RMSE | %s residual" % (m, m) for m in names) + " |")
    print("|---" * (1 + 2 * len(names)) + "|")
    for k in range(args.iterations):
        print("| %d | " % (k + 1) + " | ".join("%.4f | %.2f" % stats[m][k] for m in names) + " |")
    print()
    for m in names:
        k = int(np.argmin([s[0] for s in stats[m]]))
        print("%s: smallest RMSE %.4f after %d iterations" % (m, stats[m][k][0], k + 1))
    target = stats["ASTRA"][args.at - 1]
    ours = stats["ctrecon"]
    fit = next((k for k, s in enumerate(ours) if s[1] <= target[1]), None)
    if fit is None:
        print("ctrecon does not reach ASTRA's residual after %d iterations (%.2f) within %d iterations"
              % (args.at, target[1], args.iterations))
        return 0
    print("equal fit: ASTRA after %d iterations RMSE %.4f, residual %.2f; ctrecon first at or below that residual"
          " after %d iterations, RMSE %.4f, residual %.2f" % (args.at, target[0], target[1], fit + 1, ours[fit][0],
                                                               ours[fit][1]))
    if fit > 0 and ours[fit - 1][1] > target[1]:
        # between the two iterations that bracket ASTRA's residual, linear in the residual
        t = (ours[fit - 1][1] - target[1]) / (ours[fit - 1][1] - ours[fit][1])
        print("ctrecon's RMSE interpolated to ASTRA's residual: %.4f" % (ours[fit - 1][0] + t * (ours[fit][0] -
                                                                                              ours[fit - 1][0])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
