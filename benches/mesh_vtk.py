#!/usr/bin/env python3
"""VTK peer of ctrecon's marching cubes: vtkFlyingEdges3D on the same volume and iso-value.

Usage: mesh_vtk.py SPEC.json

SPEC.json (written by benches/mesh.rs):
  volume: path of raw little-endian float32 samples, [z][y][x] order (x fastest)
  dims: [nx, ny, nz]; spacing: [dx, dy, dz] mm; origin: [x, y, z] mm; iso: the iso-value
  threads: thread counts to ask vtkSMPTools for; rounds: runs per count (the best is printed)
Prints one JSON line per thread count: VTK's version, its SMP backend (a "Sequential" build runs on one
thread whatever is asked), the best time in ms and the number of triangles. Normals, gradients and
interpolated scalars are off: ctrecon's mesh has none of them.
"""
import json
import sys
import time

import vtk

from render_vtk import image_data


def main():
    spec = json.load(open(sys.argv[1]))
    img = image_data(spec)
    for threads in spec["threads"]:
        vtk.vtkSMPTools.Initialize(threads)
        best, tris = float("inf"), 0
        for _ in range(spec["rounds"]):
            fe = vtk.vtkFlyingEdges3D()
            fe.SetInputData(img)
            fe.SetValue(0, spec["iso"])
            fe.ComputeNormalsOff()
            fe.ComputeGradientsOff()
            fe.ComputeScalarsOff()
            t = time.perf_counter()
            fe.Update()
            best = min(best, time.perf_counter() - t)
            tris = fe.GetOutput().GetNumberOfCells()
        print(json.dumps({
            "vtk": vtk.vtkVersion.GetVTKVersion(),
            "backend": vtk.vtkSMPTools.GetBackend(),
            "threads_asked": threads,
            "threads_used": vtk.vtkSMPTools.GetEstimatedNumberOfThreads(),
            "ms": round(best * 1000, 1),
            "triangles": tris,
        }))


if __name__ == "__main__":
    main()
