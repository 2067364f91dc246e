#!/usr/bin/env python3
"""STOW-RS and WADO-RS of LIDC-IDRI-0001 into and out of ctrecon and Orthanc, side by side in one run, at two
body sizes.

Each server runs on 127.0.0.1 with a fresh data directory of its own, started anew for each body: a
`ctrecon serve` (the binary in `--bin`, else `$CARGO_TARGET_DIR/release/ctrecon`, else
`target/release/ctrecon`) and Orthanc with its DICOMweb plugin (Debian packages, `scripts/install-peers.sh
orthanc`). Two `multipart/related; type="application/dicom"` bodies are written to files once: the series'
files (`.testdata/lidc/*.dcm`, 133 instances, about 70 MB), and those files plus a copy of them as a second
series (new Study/Series/SOP Instance UIDs by DCMTK's `dcmodify`; 266 instances, about 140 MB). Each is
streamed to `POST /dicom-web/studies` of each server; then (first body) the series comes back by WADO-RS
(`GET /dicom-web/studies/{study}/series/{series}`, multipart, read and thrown away as it streams; seven
reads from each server, interleaved, the median printed). ctrecon
answers once the instances are stored and indexed and assembles each series `CTRECON_DICOM_STABLE_AGE_SECS`
(2 s) after its last instance: the bench also waits for the assembled series and reports when they were
there and the peak memory then. Printed per step: seconds, bytes, the server's peak resident memory so far
(VmHWM from /proc) and the HTTP status. One run, not a timed test; no retries.

    python3 benches/dicomweb_peers.py [--lidc .testdata/lidc] [--bin path/to/ctrecon]
"""

import argparse
import glob
import http.client
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
WADO_ROUNDS = 7
ORTHANC = "/usr/sbin/Orthanc"
PLUGIN = "/usr/share/orthanc/plugins/libOrthancDicomWeb.so"
BOUNDARY = "ctrecon-bench-boundary"
ARGS = None


def ctrecon_bin():
    if ARGS.bin:
        return ARGS.bin
    target = os.environ.get("CARGO_TARGET_DIR", os.path.join(ROOT, "target"))
    return os.path.join(target, "release", "ctrecon")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def peak_rss_mb(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def wait_http(port, path, deadline_s=60):
    t0 = time.time()
    while time.time() - t0 < deadline_s:
        try:
            c = http.client.HTTPConnection("127.0.0.1", port, timeout=2)
            c.request("GET", path)
            if c.getresponse().status < 500:
                return
        except OSError:
            pass
        time.sleep(0.1)
    raise SystemExit(f"nothing answers on port {port}")


def write_body(files, path):
    with open(path, "wb") as out:
        for f in files:
            out.write(f"--{BOUNDARY}\r\nContent-Type: application/dicom\r\n\r\n".encode())
            with open(f, "rb") as src:
                shutil.copyfileobj(src, out)
            out.write(b"\r\n")
        out.write(f"--{BOUNDARY}--\r\n".encode())
    return os.path.getsize(path)


def stow(port, body_path):
    size = os.path.getsize(body_path)
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=600)
    t0 = time.perf_counter()
    with open(body_path, "rb") as body:
        c.request("POST", "/dicom-web/studies", body=body, headers={
            "Content-Type": f'multipart/related; type="application/dicom"; boundary={BOUNDARY}',
            "Accept": "application/dicom+json",
            "Content-Length": str(size),
        })
        r = c.getresponse()
        answer = r.read()
    dt = time.perf_counter() - t0
    stored = 0
    try:
        stored = len(json.loads(answer).get("00081199", {}).get("Value", []))
    except ValueError:
        pass
    return dt, size, r.status, stored


def wado_series(port, study, series, accept):
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=600)
    t0 = time.perf_counter()
    c.request("GET", f"/dicom-web/studies/{study}/series/{series}", headers={"Accept": accept})
    r = c.getresponse()
    n = 0
    while True:
        chunk = r.read(1 << 20)
        if not chunk:
            break
        n += len(chunk)
    return time.perf_counter() - t0, n, r.status


def series_of(port):
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    c.request("GET", "/dicom-web/series?PatientID=LIDC-IDRI-0001", headers={"Accept": "application/dicom+json"})
    v = json.loads(c.getresponse().read())
    s = v[0]
    return s["0020000D"]["Value"][0], s["0020000E"]["Value"][0]


def second_series(files, tmp):
    """A copy of the series with its own study, series and SOP instance UIDs (DCMTK's dcmodify)."""
    out = os.path.join(tmp, "copy")
    os.makedirs(out)
    copies = []
    for f in files:
        dst = os.path.join(out, os.path.basename(f))
        shutil.copy(f, dst)
        copies.append(dst)
    uid = "2.25.%d" % (int.from_bytes(os.urandom(12), "big"))
    for chunk in range(0, len(copies), 40):
        subprocess.run(["dcmodify", "-nb", "-m", f"StudyInstanceUID={uid}1", "-m", f"SeriesInstanceUID={uid}2",
                        "-gin"] + copies[chunk:chunk + 40], check=True, capture_output=True)
    return copies


def start_servers(tmp, tag):
    cport = free_port()
    cdir = os.path.join(tmp, f"ctrecon-{tag}")
    env = dict(os.environ, CTRECON_DATA_DIR=cdir, CTRECON_MAX_UPLOAD_BYTES=str(1 << 30),
               CTRECON_DICOM_STABLE_AGE_SECS="2", CTRECON_LOG_FORMAT="json", RUST_LOG="warn")
    log = os.path.join(tmp, f"ctrecon-{tag}.log")
    ctrecon = subprocess.Popen([ctrecon_bin(), "serve", "--bind", f"127.0.0.1:{cport}"], env=env,
                               stdout=subprocess.DEVNULL, stderr=open(log, "w"))
    oport = free_port()
    odir = os.path.join(tmp, f"orthanc-{tag}")
    os.makedirs(os.path.join(odir, "logs"))
    cfg = {"Name": "BENCH", "StorageDirectory": os.path.join(odir, "db"), "IndexDirectory": os.path.join(odir, "db"),
           "HttpPort": oport, "RemoteAccessAllowed": False, "AuthenticationEnabled": False,
           "DicomServerEnabled": False, "Plugins": [PLUGIN],
           "DicomWeb": {"Enable": True, "Root": "/dicom-web/", "Host": f"127.0.0.1:{oport}", "Ssl": False}}
    with open(os.path.join(odir, "orthanc.json"), "w") as f:
        json.dump(cfg, f)
    orthanc = subprocess.Popen([ORTHANC, f"--logdir={os.path.join(odir, 'logs')}", os.path.join(odir, "orthanc.json")],
                               env=dict(os.environ, TCP_NODELAY="1"),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_http(cport, "/healthz")
    except SystemExit:
        sys.stderr.write(open(log).read()[-2000:])
        raise
    wait_http(oport, "/system")
    return (ctrecon, cport, cdir), (orthanc, oport)


def assembled(cdir, n, deadline_s=600):
    """Seconds until `n` series volumes are in ctrecon's data directory."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < deadline_s:
        try:
            if len([f for f in os.listdir(os.path.join(cdir, "series")) if f.endswith(".npy")]) >= n:
                return time.perf_counter() - t0
        except OSError:
            pass
        time.sleep(0.05)
    raise SystemExit("the series were not assembled")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--lidc", default=os.path.join(ROOT, ".testdata", "lidc"))
    ap.add_argument("--bin", help="the ctrecon binary (default: the release build)")
    global ARGS
    ARGS = args = ap.parse_args()
    files = sorted(glob.glob(os.path.join(args.lidc, "*.dcm")))
    if not files:
        sys.exit(f"no .dcm files under {args.lidc} (scripts/fetch-test-data.sh)")
    for need in (ctrecon_bin(), ORTHANC, PLUGIN):
        if not os.path.exists(need):
            sys.exit(f"missing {need}")
    tmp = tempfile.mkdtemp(prefix="dicomweb-bench-")
    procs = []
    try:
        bodies = []
        for tag, parts, series in (("1x", files, 1), ("2x", files + second_series(files, tmp), 2)):
            body = os.path.join(tmp, f"stow-{tag}.body")
            bodies.append((tag, body, write_body(parts, body), len(parts), series))
        print(f"LIDC-IDRI-0001: {len(files)} instances; bodies " +
              ", ".join(f"{n} instances {size / 1e6:.1f} MB" for _, _, size, n, _ in bodies) +
              f"; load {open('/proc/loadavg').read().split()[0]}")
        rows = []
        for tag, body, size, n, series in bodies:
            (ctrecon, cport, cdir), (orthanc, oport) = start_servers(tmp, tag)
            procs += [ctrecon, orthanc]
            for name, port, proc in (("ctrecon", cport, ctrecon), ("Orthanc", oport, orthanc)):
                dt, n, status, stored = stow(port, body)
                rows.append((name, f"STOW-RS {tag}", dt, n, status, f"{stored} stored", peak_rss_mb(proc.pid)))
            t = assembled(cdir, series)
            rows.append(("ctrecon", f"assembled {tag}", t, 0, 200,
                         f"{series} series, s after the answer (stable age 2 s)", peak_rss_mb(ctrecon.pid)))
            if tag == "1x":
                servers = (
                    ("ctrecon", cport, ctrecon, 'multipart/related; type="application/dicom"; transfer-syntax=*'),
                    ("Orthanc", oport, orthanc, 'multipart/related; type="application/dicom"'),
                )
                uids = {name: series_of(port) for name, port, _, _ in servers}
                times = {name: [] for name, _, _, _ in servers}
                for _ in range(WADO_ROUNDS):
                    for name, port, proc, accept in servers:
                        dt, n, status = wado_series(port, *uids[name], accept)
                        times[name].append((dt, n, status))
                for name, port, proc, accept in servers:
                    ts = sorted(times[name])
                    dt, n, status = ts[len(ts) // 2]
                    rows.append((name, "WADO-RS series", dt, n, max(t[2] for t in ts),
                                 f"median of {WADO_ROUNDS}, interleaved (best {ts[0][0]:.3f} s)",
                                 peak_rss_mb(proc.pid)))
            for p in (ctrecon, orthanc):
                p.terminate()
                p.wait(timeout=30)
        print(f"{'server':8} {'step':15} {'seconds':>8} {'MB':>7} {'MB/s':>7} {'status':>6} {'peak RSS MB':>11}  note")
        for name, step, dt, n, status, note, rss in rows:
            rate = f"{n / 1e6 / dt:7.1f}" if n else f"{'':7}"
            print(f"{name:8} {step:15} {dt:8.3f} {n / 1e6:7.1f} {rate} {status:6d} {rss:11.0f}  {note}")
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
