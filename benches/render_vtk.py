#!/usr/bin/env python3
"""VTK peer of ctrecon's renderer: the same volume and orthographic camera rendered offscreen by VTK.

Usage: render_vtk.py SPEC.json

SPEC.json (written by tests/render_vtk.rs or benches/render.rs):
  volume: path of raw little-endian float32 samples, [z][y][x] order (x fastest)
  dims: [nx, ny, nz]; spacing: [dx, dy, dz] mm; origin: [x, y, z] mm (axis-aligned LPS frame)
  camera: {eye: [..], centre: [..], up: [..], parallel_scale: half the image height in mm}
  width, height: pixels
  iso: iso-value of the surface (mode "silhouette")
  mode: "silhouette" writes `out` (height*width uint8, top row first, 255 where the surface is seen);
        "raycast" times vtkFixedPointVolumeRayCastMapper (VTK's CPU ray caster) over `frames` views
        turned by 360/frames degrees of azimuth, with the transfer function `points`
        ([[value, r, g, b, opacity per mm], ...]) and sample distance `step_mm`.
Prints one JSON line: {"vtk": version, "mode": ..., "ms_per_frame": ...}.
"""
import json
import sys
import time

import numpy as np
import vtk
from vtk.util import numpy_support


def image_data(spec):
    nx, ny, nz = spec["dims"]
    raw = np.fromfile(spec["volume"], dtype="<f4")
    if raw.size != nx * ny * nz:
        raise SystemExit(f"{spec['volume']}: {raw.size} samples, want {nx * ny * nz}")
    img = vtk.vtkImageData()
    img.SetDimensions(nx, ny, nz)
    img.SetSpacing(*spec["spacing"])
    img.SetOrigin(*spec["origin"])
    arr = numpy_support.numpy_to_vtk(raw, deep=True, array_type=vtk.VTK_FLOAT)
    arr.SetName("values")
    img.GetPointData().SetScalars(arr)
    return img


def window(spec, renderer):
    win = vtk.vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.SetSize(spec["width"], spec["height"])
    win.AddRenderer(renderer)
    cam = renderer.GetActiveCamera()
    c = spec["camera"]
    cam.ParallelProjectionOn()
    cam.SetPosition(*c["eye"])
    cam.SetFocalPoint(*c["centre"])
    cam.SetViewUp(*c["up"])
    cam.SetParallelScale(c["parallel_scale"])
    renderer.ResetCameraClippingRange()
    return win


def grab(win):
    w2i = vtk.vtkWindowToImageFilter()
    w2i.SetInput(win)
    w2i.SetInputBufferTypeToRGB()
    w2i.ReadFrontBufferOff()
    w2i.Update()
    out = w2i.GetOutput()
    w, h, _ = out.GetDimensions()
    rgb = numpy_support.vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, 3)
    return rgb[::-1]  # VTK's first row is the bottom one


def silhouette(spec):
    img = image_data(spec)
    surf = vtk.vtkFlyingEdges3D()
    surf.SetInputData(img)
    surf.SetValue(0, spec["iso"])
    mapper = vtk.vtkPolyDataMapper()
    mapper.SetInputConnection(surf.GetOutputPort())
    mapper.ScalarVisibilityOff()
    actor = vtk.vtkActor()
    actor.SetMapper(mapper)
    prop = actor.GetProperty()
    prop.SetColor(1, 1, 1)
    prop.SetAmbient(1.0)
    prop.SetDiffuse(0.0)
    prop.SetSpecular(0.0)
    ren = vtk.vtkRenderer()
    ren.SetBackground(0, 0, 0)
    ren.AddActor(actor)
    win = window(spec, ren)
    t0 = time.perf_counter()
    win.Render()
    ms = (time.perf_counter() - t0) * 1000
    rgb = grab(win)
    mask = np.where(rgb[:, :, 0] > 127, 255, 0).astype(np.uint8)
    mask.tofile(spec["out"])
    return ms


def raycast(spec):
    img = image_data(spec)
    colour = vtk.vtkColorTransferFunction()
    opacity = vtk.vtkPiecewiseFunction()
    for v, r, g, b, a in spec["points"]:
        colour.AddRGBPoint(v, r, g, b)
        opacity.AddPoint(v, a)
    prop = vtk.vtkVolumeProperty()
    prop.SetColor(colour)
    prop.SetScalarOpacity(opacity)
    prop.SetScalarOpacityUnitDistance(1.0)
    prop.SetInterpolationTypeToLinear()
    prop.ShadeOn()
    prop.SetAmbient(0.2)
    prop.SetDiffuse(0.7)
    prop.SetSpecular(0.3)
    prop.SetSpecularPower(20)
    mapper = vtk.vtkFixedPointVolumeRayCastMapper()
    mapper.SetInputData(img)
    mapper.SetSampleDistance(spec["step_mm"])
    mapper.AutoAdjustSampleDistancesOff()
    volume = vtk.vtkVolume()
    volume.SetMapper(mapper)
    volume.SetProperty(prop)
    ren = vtk.vtkRenderer()
    ren.SetBackground(0, 0, 0)
    ren.AddVolume(volume)
    win = window(spec, ren)
    win.Render()  # first frame builds VTK's own tables; timed frames follow
    frames = spec.get("frames", 4)
    t0 = time.perf_counter()
    for _ in range(frames):
        ren.GetActiveCamera().Azimuth(360.0 / frames)
        win.Render()
    return (time.perf_counter() - t0) * 1000 / frames


def main():
    spec = json.load(open(sys.argv[1]))
    ms = silhouette(spec) if spec["mode"] == "silhouette" else raycast(spec)
    print(json.dumps({"vtk": vtk.vtkVersion.GetVTKVersion(), "mode": spec["mode"], "ms_per_frame": ms}))


if __name__ == "__main__":
    main()
