#!/usr/bin/env python3
"""ctrecon against its CPU peers on the same analytic data, one case after the other in one sitting.

For every case, `ctrecon phantom` writes the exact projections of the modified Shepp-Logan phantom
(line integrals of the analytic ellipses or ellipsoids, no voxelised phantom) and the phantom itself
(point-sampled 4x4 per pixel in 2D, 2x2x2 per voxel in 3D); every peer and the `ctrecon recon` CLI
then reconstruct the same `.npy` file. Printed per run: seconds and RMSE over the inscribed disk
(2D) or cylinder (3D) against the phantom (values 0-1), and the ratio of the peer's seconds to
ctrecon's. Last, `ctrecon mesh` and VTK's flying edges mesh the rasterised 3D phantom at 0.5; the RMSE
column then holds the number of triangles.

The cone-beam iterative cases run twice: on the exact projections and on the same projections with
Gaussian noise of 1 % of their largest value added (fixed seed, one `.npy` both programs read). RTK
runs each of them twice: with its default projector pair (`rtk`: Joseph forward projection, voxel-based
back projection, which is not the forward projection's transpose) and with its matched pair
(`rtk_joseph`: Joseph forward and Joseph back projection, the transpose), which is the pair ctrecon's
iterative methods use by default; the rows "..., voxel-driven back projection" run ctrecon's CGLS with
`"back_projector": "voxel"` (RTK's default pair, conjugate gradients on B A x = B b) beside RTK's default.

Timing: ctrecon is timed as a whole process (read the `.npy`, reconstruct, write the `.npy`); the
peers only around their reconstruction call (data already in memory, imports done), which favours
the peers. Memory (column *peak MB*): ctrecon's peak resident memory as a process (`/usr/bin/time`);
each peer runs in a forked child, and its figure is that child's peak resident memory above what it
held when it started (the data already loaded), which again favours the peers. Threads: ctrecon uses
every core (rayon), RTK is given as many (`--threads`), ASTRA's CPU algorithms and scikit-image run on one.

Conventions, checked once against ctrecon's FBP/FDK of the same data: ASTRA and scikit-image take
ctrecon's parallel angles negated; RTK takes the cone angles as they are, and its volume maps to
ctrecon's `[z][y][x]` by swapping its first two axes and reversing the second. ASTRA's CPU FBP takes
parallel beams only, so for the fan-beam case (`astra_fan`) the fan data are rebinned to parallel rays
in numpy first, and the rebinning is timed with the reconstruction.

Run through `run.sh`, which installs the pinned peers in `benches/peers/.venv` and builds ctrecon.
"""

import argparse
import json
import math
import os
import pickle
import sys
import time

import numpy as np

from common import cone_case, fan_case, loadavg, parallel_case, timed

HERE = os.path.dirname(os.path.abspath(__file__))


def ctrecon_bin():
    target = os.environ.get("CARGO_TARGET_DIR", os.path.join(HERE, "..", "..", "target"))
    return os.path.join(target, "release", "ctrecon")


def run_ctrecon(args):
    return run_ctrecon_rss(args)[0]


def run_ctrecon_rss(args):
    """(seconds, peak resident bytes) of one `ctrecon` process."""
    return timed([ctrecon_bin(), *args])


def status_kb(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return 0


def in_child(fn, *args):
    """`fn(*args)` in a forked child: (its result, the child's peak resident bytes above its start).
    Raises what the child raised, as a RuntimeError with its message."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # reset the peak (VmHWM) to the current resident size
            start = status_kb("VmRSS")
            res = fn(*args)
            out = (res, (status_kb("VmHWM") - start) * 1024, None)
        except Exception as e:  # handed to the parent
            out = (None, 0, "%s: %s" % (type(e).__name__, e))
        with os.fdopen(w, "wb") as f:
            pickle.dump(out, f)
        os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        res, peak, err = pickle.load(f)
    os.waitpid(pid, 0)
    if err:
        raise RuntimeError(err)
    return res, peak


# ----------------------------------------------------------------------------------------------
# Cases: sizes per mode.


def cases(quick):
    if quick:
        par, fan, it2, fdk, cone = (256, 360, 363), (256, 360, 400), (128, 180, 183), [(64, 90, 96)], (48, 90, 72)
    else:
        par, fan, it2, fdk, cone = ((512, 720, 725), (512, 720, 800), (256, 360, 363),
                                    [(128, 360, 256), (256, 360, 512)], (128, 360, 256))
    out = [
        ("parallel FBP %d² / %d" % par[:2], parallel_case(*par), "fbp", {}, ["skimage", "astra"]),
        ("fan-beam FBP, flat, %d² / %d" % fan[:2], fan_case(*fan), "fbp", {}, ["astra_fan"]),
        ("SART x10, %d² / %d" % it2[:2], parallel_case(*it2), "sart", {"iterations": 10}, ["astra"]),
        ("CGLS x50, %d² / %d" % it2[:2], parallel_case(*it2), "cgls", {"iterations": 50}, ["astra"]),
    ]
    for c in fdk:
        out.append(("FDK %d³ from %d x %d²" % c, cone_case(*c), "fdk", {}, ["rtk"]))
    for noise in (0.0, 0.01):
        tail = ", noise 1 %" if noise else ""
        for name, algorithm in (("SIRT", "sirt"), ("CGLS", "cgls")):
            case = dict(cone_case(*cone), noise=noise)
            out.append(("cone %s x10, %d³ from %d x %d²%s" % ((name,) + cone + (tail,)), case, algorithm,
                        {"iterations": 10}, ["rtk", "rtk_joseph"]))
        # ctrecon with RTK's default pair (voxel-driven back projection) beside RTK's default.
        case = dict(cone_case(*cone), noise=noise, output="_voxel")
        out.append(("cone CGLS x10, %d³ from %d x %d²%s, voxel-driven back projection" % (cone + (tail,)), case,
                    "cgls", {"iterations": 10, "back_projector": "voxel"}, ["rtk"]))
    return out


# ----------------------------------------------------------------------------------------------
# Peers: each returns (seconds of the reconstruction call, image in ctrecon's array order).


def angles(case):
    g = case["geometry"]
    full = np.pi if g["type"] == "parallel" else 2 * np.pi
    k = g["angles"]["count"]
    return np.arange(k) * full / k


def skimage_fbp(case, data, algorithm, params):
    from skimage.transform import iradon

    t = time.perf_counter()
    img = iradon(data.T, theta=-np.degrees(angles(case)), filter_name="ramp", circle=True,
                 output_size=case["n"])
    return time.perf_counter() - t, img


def astra_2d(case, data, algorithm, params):
    import astra

    n = case["n"]
    vg = astra.create_vol_geom(n, n)
    pg = astra.create_proj_geom("parallel", 1.0, data.shape[1], -angles(case))
    pid = astra.create_projector("linear", pg, vg)
    sid = astra.data2d.create("-sino", pg, data)
    rid = astra.data2d.create("-vol", vg, 0)
    name = {"fbp": "FBP", "sart": "SART", "cgls": "CGLS"}[algorithm]
    cfg = astra.astra_dict(name)
    cfg.update(ProjectorId=pid, ProjectionDataId=sid, ReconstructionDataId=rid)
    iterations = params.get("iterations", 1)
    if algorithm == "sart":
        cfg["option"] = {"ProjectionOrder": "random"}
        iterations *= data.shape[0]  # ASTRA's SART iteration is one view
    alg = astra.algorithm.create(cfg)
    t = time.perf_counter()
    astra.algorithm.run(alg, iterations)
    secs = time.perf_counter() - t
    img = astra.data2d.get(rid)
    for f, i in ((astra.algorithm.delete, alg), (astra.data2d.delete, rid), (astra.data2d.delete, sid),
                 (astra.projector.delete, pid)):
        f(i)
    return secs, img


def astra_fan(case, data, algorithm, params):
    """ASTRA's CPU FBP takes parallel beams only: the fan data are rebinned to parallel rays (bilinear in
    view and element, numpy; 1 mm apart, half as many views over 180°), then reconstructed by
    [`astra_2d`]; both are timed."""
    g = case["geometry"]
    dso, dsd, det = g["dso_mm"], g["dsd_mm"], g["detector"]
    views, m = data.shape
    t = time.perf_counter()
    # The fan ray of view β and element u is the parallel ray of angle θ = β − γ at s = DSO·sin γ,
    # γ = atan(u / DSD), in ctrecon's conventions (`geometry::fan_view`).
    gamma_max = math.atan((m / 2) * det["spacing_mm"] / dsd)
    half = int(dso * math.sin(gamma_max))
    s = np.arange(-half, half + 1, dtype=np.float64)
    theta = np.arange(views // 2) * (np.pi / (views // 2))
    gamma = np.arcsin(s / dso)
    beta = np.mod(theta[:, None] + gamma[None, :], 2 * np.pi) / (2 * np.pi / views)
    u = (dsd * np.tan(gamma) - det["offset_mm"]) / det["spacing_mm"] + (m - 1) / 2
    b0 = np.floor(beta).astype(np.int64)
    fb = beta - b0
    u0 = np.floor(u).astype(np.int64)
    fu = np.broadcast_to(u - u0, beta.shape)
    b0, b1 = b0 % views, (b0 + 1) % views
    inside = (u0 >= 0) & (u0 + 1 < m)
    u0c = np.broadcast_to(np.clip(u0, 0, m - 2), beta.shape)
    rows = (1 - fb) * ((1 - fu) * data[b0, u0c] + fu * data[b0, u0c + 1]) + \
        fb * ((1 - fu) * data[b1, u0c] + fu * data[b1, u0c + 1])
    sino = np.where(inside[None, :], rows, 0.0).astype(np.float32)
    rebin = time.perf_counter() - t
    parallel = parallel_case(case["n"], views // 2, s.size)
    secs, img = astra_2d(parallel, sino, algorithm, params)
    return rebin + secs, img


def load_peer_libraries(names):
    """Import the peers' libraries and resolve the classes they use (ITK loads its modules lazily), before
    any child is forked: a peer's memory then counts its work, not its libraries."""
    if "skimage" in names:
        import skimage.transform  # noqa: F401
    if "astra" in names or "astra_fan" in names:
        import astra  # noqa: F401
    if "rtk" in names:
        import itk
        from itk import RTK as rtk

        image = itk.Image[itk.F, 3]
        for cls in (rtk.ThreeDCircularProjectionGeometry, rtk.ConstantImageSource[image],
                    rtk.FDKConeBeamReconstructionFilter[image], rtk.SARTConeBeamReconstructionFilter[image, image],
                    rtk.ConjugateGradientConeBeamReconstructionFilter[image],
                    rtk.JosephBackProjectionImageFilter[image, image]):
            cls.New()
        itk.image_from_array(np.zeros((2, 2, 2), dtype=np.float32))
    if "vtk" in names:
        import vtk  # noqa: F401
        from vtk.util import numpy_support  # noqa: F401

        vtk.vtkFlyingEdges3D()


def rtk_3d(case, data, algorithm, params, threads, matched=False):
    """RTK's FDK, SART (all views per subset: SIRT) or conjugate gradient; the iterative filters with
    RTK's default projectors (Joseph forward, voxel-based back) or, `matched`, with the Joseph back
    projector, the transpose of the forward projector."""
    import itk
    from itk import RTK as rtk

    itk.MultiThreaderBase.SetGlobalDefaultNumberOfThreads(threads)
    g = case["geometry"]
    n, det = case["n"], g["detector"]
    geometry = rtk.ThreeDCircularProjectionGeometry.New()
    for a in np.degrees(angles(case)):
        geometry.AddProjection(g["dso_mm"], g["dsd_mm"], float(a), 0.0, 0.0)
    image = itk.Image[itk.F, 3]
    proj = itk.image_from_array(np.ascontiguousarray(data, dtype=np.float32))
    proj.SetOrigin([-(det["nu"] - 1) / 2 * det["du_mm"], -(det["nv"] - 1) / 2 * det["dv_mm"], 0.0])
    proj.SetSpacing([det["du_mm"], det["dv_mm"], 1.0])
    source = rtk.ConstantImageSource[image].New()
    source.SetOrigin([-(n - 1) / 2.0] * 3)
    source.SetSpacing([1.0] * 3)
    source.SetSize([n] * 3)
    source.SetConstant(0.0)
    if algorithm == "fdk":
        f = rtk.FDKConeBeamReconstructionFilter[image].New()
    elif algorithm == "sirt":
        f = rtk.SARTConeBeamReconstructionFilter[image, image].New()
        f.SetNumberOfIterations(params["iterations"])
        f.SetNumberOfProjectionsPerSubset(data.shape[0])
        f.SetLambda(1.0)
    else:
        f = rtk.ConjugateGradientConeBeamReconstructionFilter[image].New()
        f.SetNumberOfIterations(params["iterations"])
    if matched and algorithm != "fdk":
        f.SetBackProjectionFilter(f.BackProjectionType_BP_JOSEPH)
    f.SetInput(0, source.GetOutput())
    f.SetInput(1, proj)
    if algorithm == "cgls":
        ones = itk.image_from_array(np.ones_like(data, dtype=np.float32))
        ones.CopyInformation(proj)
        f.SetInput(2, ones)
    f.SetGeometry(geometry)
    t = time.perf_counter()
    f.Update()
    secs = time.perf_counter() - t
    vol = itk.array_from_image(f.GetOutput())
    return secs, np.ascontiguousarray(vol.transpose(1, 0, 2)[:, ::-1, :])


# ----------------------------------------------------------------------------------------------


def vtk_flying_edges(volume, iso):
    """vtkFlyingEdges3D on `volume` ([z][y][x], 1 mm voxels): seconds of Update() and triangles."""
    import vtk
    from vtk.util import numpy_support

    nz, ny, nx = volume.shape
    img = vtk.vtkImageData()
    img.SetDimensions(nx, ny, nz)
    img.GetPointData().SetScalars(numpy_support.numpy_to_vtk(
        np.ascontiguousarray(volume, dtype=np.float32).ravel(), deep=True, array_type=vtk.VTK_FLOAT))
    fe = vtk.vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, iso)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    t = time.perf_counter()
    fe.Update()
    return time.perf_counter() - t, fe.GetOutput().GetNumberOfCells(), vtk.vtkSMPTools.GetBackend()


def mesh_case(n, work):
    """Marching cubes of the rasterised 3D phantom at 0.5 (its skull), ctrecon's `mesh` command (whole
    process: read the `.npy`, mesh, write the STL) against VTK's flying edges (its Update() only)."""
    name = "marching cubes %d³, iso 0.5" % n
    ref_path = os.path.join(work, "phantom3_%d.npy" % n)
    if not os.path.exists(ref_path):
        run_ctrecon(["phantom", "--dims", "3", "--size", str(n), "--fov-mm", str(n), "--supersample", "2",
                     "--out", ref_path])
    out = os.path.join(work, "mesh_%d.stl" % n)
    load = loadavg()
    secs, rss = run_ctrecon_rss(["mesh", "--input", ref_path, "--iso", "0.5", "--all-components", "--out", out])
    tris = (os.path.getsize(out) - 84) // 50
    print("| %s | ctrecon | %.3f | %d triangles | %.0f | | %s |" % (name, secs, tris, rss / 1e6, load), flush=True)
    load = loadavg()
    try:
        (s, peer_tris, backend), peak = in_child(vtk_flying_edges, np.load(ref_path), 0.5)
    except Exception as e:
        print("| %s | VTK flying edges | failed: %s | | | | %s |" % (name, str(e).splitlines()[0], load))
        return
    print("| %s | VTK flying edges (%s) | %.3f | %d triangles | %.0f | %.1fx | %s |"
          % (name, backend, s, peer_tris, peak / 1e6, s / secs, load), flush=True)


def case_files(case, algorithm, work):
    """Write the case's geometry, grid, projections (with the case's noise) and phantom into `work` where
    missing: (data path, phantom path, geometry path, grid path, ctrecon's output path, data, phantom)."""
    tag = "%s_%s_%d" % (algorithm, case["geometry"]["type"], case["n"])
    geo, clean_path = os.path.join(work, tag + ".json"), os.path.join(work, tag + ".npy")
    noise = case.get("noise", 0.0)
    data_path = clean_path
    if noise:
        tag += "_noise%g" % noise
        data_path = os.path.join(work, tag + ".npy")
    ref_path = os.path.join(work, "phantom%d_%d.npy" % (case["dims"], case["n"]))
    with open(geo, "w") as f:
        json.dump(case["geometry"], f)
    n = case["n"]
    if not os.path.exists(clean_path):
        run_ctrecon(["phantom", "--geometry", geo, "--fov-mm", str(n), "--out", clean_path])
    if not os.path.exists(data_path):
        clean = np.load(clean_path)
        rng = np.random.default_rng(1)
        noisy = clean + rng.normal(0.0, noise * float(clean.max()), clean.shape)
        np.save(data_path, noisy.astype(np.float32))
    if not os.path.exists(ref_path):
        run_ctrecon(["phantom", "--dims", str(case["dims"]), "--size", str(n), "--fov-mm", str(n),
                     "--supersample", "4" if case["dims"] == 2 else "2", "--out", ref_path])
    data, ref = np.load(data_path), np.load(ref_path)
    out = os.path.join(work, tag + case.get("output", "") + "_ctrecon.npy")
    grid = os.path.join(work, tag + "_grid.json")
    with open(grid, "w") as f:
        if case["dims"] == 2:
            json.dump({"nx": n, "ny": n, "dx_mm": 1.0, "dy_mm": 1.0}, f)
        else:
            json.dump({"nx": n, "ny": n, "nz": n, "spacing_mm": [1.0, 1.0, 1.0]}, f)
    return data_path, ref_path, geo, grid, out, data, ref


def rmse(img, ref):
    """RMSE over the inscribed disk (2D) or cylinder (3D) of the last two axes."""
    n = ref.shape[-1]
    c = (np.arange(n) - (n - 1) / 2) / (n / 2)
    mask = (c[:, None] ** 2 + c[None, :] ** 2) <= 1.0
    d = (np.asarray(img, dtype=np.float64) - ref)[..., mask]
    return float(np.sqrt(np.mean(d ** 2)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (under two minutes)")
    ap.add_argument("--threads", type=int, default=os.cpu_count(), help="threads for RTK")
    ap.add_argument("--only", help="run only the cases whose name contains this text")
    ap.add_argument("--work", default=os.path.join(HERE, "work"), help="folder for the .npy files")
    args = ap.parse_args()
    os.makedirs(args.work, exist_ok=True)
    peers = {"skimage": skimage_fbp, "astra": astra_2d, "astra_fan": astra_fan,
             "rtk": lambda *a: rtk_3d(*a, threads=args.threads),
             "rtk_joseph": lambda *a: rtk_3d(*a, threads=args.threads, matched=True)}
    print("# %s, %d CPUs, load average %s at start" % (time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                                                      os.cpu_count(), loadavg()))
    print("| case | program | seconds | RMSE | peak MB | peer s / ctrecon s | load |")
    print("|---|---|---|---|---|---|---|")
    chosen = [c for c in cases(args.quick) if not args.only or args.only in c[0]]
    load_peer_libraries({p for c in chosen for p in c[4]})
    for name, case, algorithm, params, names in chosen:
        data_path, _, geo, grid, out, data, ref = case_files(case, algorithm, args.work)
        load = loadavg()
        secs, rss = run_ctrecon_rss(["recon", "--input", data_path, "--geometry", geo, "--algorithm", algorithm,
                                     "--params", json.dumps(params), "--grid", grid, "--output", out])
        ours = rmse(np.load(out), ref)
        print("| %s | ctrecon | %.3f | %.4f | %.0f | | %s |" % (name, secs, ours, rss / 1e6, load), flush=True)
        for peer in names:
            load = loadavg()
            try:
                (s, img), peak = in_child(peers[peer], case, data, algorithm, params)
            except Exception as e:  # a peer that cannot run this case says so and the rest go on
                print("| %s | %s | failed: %s | | | | %s |" % (name, peer, str(e).splitlines()[0], load))
                continue
            print("| %s | %s | %.3f | %.4f | %.0f | %.1fx | %s |"
                  % (name, peer, s, rmse(img, ref), peak / 1e6, s / secs, load), flush=True)
    n = 128 if args.quick else 256
    if not args.only or args.only in "marching cubes %d³, iso 0.5" % n:
        load_peer_libraries({"vtk"})
        mesh_case(n, args.work)
    return 0


if __name__ == "__main__":
    sys.exit(main())
