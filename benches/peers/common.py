"""What `peers.py` and `scaling.py` share (standard library only): the analytic cases' geometries, one timed
process with its peak memory, and the load average."""

import math
import os
import subprocess
import tempfile
import time


def parallel_case(n, views, det):
    return {"dims": 2, "n": n, "geometry": {"type": "parallel", "angles": {"count": views},
                                            "det_count": det, "det_spacing_mm": 1.0}}


def fan_case(n, views, det):
    """A fan beam over 360° with a flat detector, for 1 mm pixels over n mm: DSO 2n, DSD 3n (magnification
    1.5), `det` elements reaching the corners of the square with 2 % to spare."""
    dso, dsd = 2.0 * n, 3.0 * n
    half = dsd * math.tan(math.asin(1.02 * n / math.sqrt(2.0) / dso))
    return {"dims": 2, "n": n, "geometry": {
        "type": "fan", "angles": {"count": views}, "dso_mm": dso, "dsd_mm": dsd,
        "detector": {"shape": "flat", "count": det, "spacing_mm": 2.0 * half / det, "offset_mm": 0.0}}}


def cone_case(n, views, det):
    """The scaled cone beam of the iterative examples: 1 mm voxels, n mm field of view, detector
    pitch 1.5*128/n mm at DSD 750*n/128 (magnification 1.5)."""
    pitch = 1.5 * 128.0 / n
    return {"dims": 3, "n": n, "geometry": {
        "type": "cone", "angles": {"count": views}, "dso_mm": 500.0 * n / 128, "dsd_mm": 750.0 * n / 128,
        "detector": {"nu": det, "nv": det, "du_mm": pitch, "dv_mm": pitch, "offset_u_mm": 0,
                     "offset_v_mm": 0}}}


def timed(cmd, env=None):
    """(seconds, peak resident bytes) of the process `cmd`, under `/usr/bin/time`; its output discarded."""
    with tempfile.NamedTemporaryFile("r") as f:
        t = time.perf_counter()
        subprocess.run(["/usr/bin/time", "-f", "%M", "-o", f.name, *cmd], check=True, env=env,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        secs = time.perf_counter() - t
        kb = f.read().split()[-1]
    return secs, int(kb) * 1024


def loadavg():
    with open("/proc/loadavg") as f:
        return f.read().split()[0]
