#!/usr/bin/env python3
"""C-STORE of LIDC-IDRI-0001 into ctrecon, DCMTK's storescp and Orthanc side by side in one run, ctrecon's
memory while it receives, and the derived series sent from ctrecon and from Orthanc.

Every server runs on 127.0.0.1 with a fresh directory of its own: a `ctrecon serve` with its DICOM node (the
binary in `--bin`, else `$CARGO_TARGET_DIR/release/ctrecon`, else `target/release/ctrecon`), `storescp`
(DCMTK, writing each instance to a file) and Orthanc (Debian packages, `scripts/install-peers.sh`). Every
DCMTK tool and Orthanc run with `TCP_NODELAY=1` (ctrecon sets it on its own sockets), else each round trip
costs Nagle's delay and the figures measure that.

1. Receive: `storescu +sd` sends the series' files (`.testdata/lidc/*.dcm`, 133 instances, about 70 MB) to each
   receiver in turn, `--rounds` times (receivers interleaved; Orthanc's copy deleted between rounds, since it
   skips instances it holds). Printed: each receiver's median and best wall time of storescu.
2. Memory: ctrecon's resident memory before the first round (VmRSS) and its peak until the last round ends
   (VmHWM), against the size of one instance. Its stable age is long enough that no series is assembled
   while the rounds run, so the peak is receiving alone.
3. Send: once the series is stable, ctrecon assembles it and a rule sends its volume as a derived CT series
   (133 instances) to Orthanc; the bench then times a second delivery of the same results to a fresh copy in
   Orthanc and one to storescp (from each delivery's `created_at` to `finished_at`: the sending alone, the
   export being made by the first), and Orthanc sending the series it received to storescp
   (`POST /modalities/STORESCP/store`, synchronous, the request's wall time).

One run, not a timed test; no retries.

    python3 benches/dimse_peers.py [--lidc .testdata/lidc] [--bin path/to/ctrecon] [--rounds 3]
"""

import argparse
import datetime
import glob
import http.client
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
ORTHANC = "/usr/sbin/Orthanc"
NODELAY = dict(os.environ, TCP_NODELAY="1")
STABLE_AGE_SECS = 60


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def proc_kb(pid, key):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return 0


def http_json(port, method, path, body=None, timeout=600):
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    data = None if body is None else json.dumps(body).encode()
    c.request(method, path, body=data, headers={"Content-Type": "application/json"} if data else {})
    r = c.getresponse()
    raw = r.read()
    try:
        return r.status, json.loads(raw) if raw else None
    except ValueError:
        return r.status, raw


def wait_until(what, check, deadline_s=300, step=0.2):
    t0 = time.time()
    while time.time() - t0 < deadline_s:
        v = check()
        if v:
            return v
        time.sleep(step)
    raise SystemExit(f"timed out waiting for {what}")


def wait_http(port, path):
    def up():
        try:
            return http_json(port, "GET", path, timeout=2)[0] < 500
        except OSError:
            return False
    wait_until(f"port {port}", up, 60, 0.1)


def wait_port(port):
    def up():
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                return True
        except OSError:
            return False
    wait_until(f"port {port}", up, 60, 0.1)


def storescu(port, called, src):
    t0 = time.perf_counter()
    out = subprocess.run(["storescu", "-aet", "SCANNER", "-aec", called, "+sd", "127.0.0.1", str(port), src],
                         env=NODELAY, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if out.returncode != 0:
        raise SystemExit(f"storescu to {called} failed: {out.stderr[-2000:]}")
    return dt


def rfc3339(s):
    return datetime.datetime.fromisoformat(s.replace("Z", "+00:00")).timestamp()


def delivery(cport, job, dest):
    status, d = http_json(cport, "POST", "/v1/deliveries", {"job_id": job, "destination": dest})
    if status not in (200, 201, 202):
        raise SystemExit(f"delivery to {dest}: {status} {d}")
    did = d["id"]

    def done():
        v = http_json(cport, "GET", f"/v1/deliveries/{did}")[1]
        return v if v["state"] in ("succeeded", "failed") else None
    d = wait_until(f"the delivery to {dest}", done, 600, 0.05)
    return rfc3339(d["finished_at"]) - rfc3339(d["created_at"]), d


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--lidc", default=os.path.join(ROOT, ".testdata", "lidc"))
    ap.add_argument("--bin", help="the ctrecon binary (default: the release build)")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    binary = args.bin or os.path.join(os.environ.get("CARGO_TARGET_DIR", os.path.join(ROOT, "target")),
                                      "release", "ctrecon")
    files = sorted(glob.glob(os.path.join(args.lidc, "*.dcm")))
    if not files:
        sys.exit(f"no .dcm files under {args.lidc} (scripts/fetch-test-data.sh)")
    for need in (binary, ORTHANC, shutil.which("storescu") or "storescu", shutil.which("storescp") or "storescp"):
        if not os.path.exists(need):
            sys.exit(f"missing {need}")
    sizes = [os.path.getsize(f) for f in files]
    tmp = tempfile.mkdtemp(prefix="dimse-bench-")
    procs = []
    try:
        src = os.path.join(tmp, "series")
        os.makedirs(src)
        for f in files:
            shutil.copy(f, src)
        print(f"LIDC-IDRI-0001: {len(files)} instances, {sum(sizes) / 1e6:.1f} MB, largest {max(sizes) / 1e6:.2f} MB; "
              f"load {open('/proc/loadavg').read().split()[0]}")

        # storescp, writing every instance to a file.
        scp_port = free_port()
        scp_dir = os.path.join(tmp, "storescp")
        os.makedirs(scp_dir)
        scp = subprocess.Popen(["storescp", "--aetitle", "STORESCP", "--output-directory", scp_dir, str(scp_port)],
                               env=NODELAY, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(scp)

        # Orthanc, knowing storescp.
        o_http, o_dicom = free_port(), free_port()
        odir = os.path.join(tmp, "orthanc")
        os.makedirs(os.path.join(odir, "logs"))
        cfg = {"Name": "BENCH", "StorageDirectory": os.path.join(odir, "db"), "IndexDirectory": os.path.join(odir, "db"),
               "HttpPort": o_http, "RemoteAccessAllowed": False, "AuthenticationEnabled": False,
               "DicomServerEnabled": True, "DicomAet": "ORTHANC", "DicomPort": o_dicom,
               "DicomCheckCalledAet": False, "DicomAlwaysAllowStore": True, "DicomAlwaysAllowEcho": True,
               "DicomCheckModalityHost": False,
               "DicomModalities": {"STORESCP": ["STORESCP", "127.0.0.1", scp_port]}}
        with open(os.path.join(odir, "orthanc.json"), "w") as f:
            json.dump(cfg, f)
        orthanc = subprocess.Popen([ORTHANC, f"--logdir={os.path.join(odir, 'logs')}", os.path.join(odir, "orthanc.json")],
                                   env=NODELAY, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(orthanc)

        # ctrecon with its node; SCANNER may call it, ORTHANC and STORESCP are destinations.
        c_http, c_dicom = free_port(), free_port()
        cdir = os.path.join(tmp, "ctrecon")
        peer = lambda ae, port: {"ae_title": ae, "host": "127.0.0.1", "port": port}
        config = {"data_dir": cdir, "dicom": {
            "port": c_dicom, "stable_age_secs": STABLE_AGE_SECS,
            "peers": [peer("SCANNER", 1), peer("ORTHANC", o_dicom), peer("STORESCP", scp_port)],
            "rules": [{"name": "bench", "send_volume": True, "destinations": ["ORTHANC"],
                       "job": {"products": [{"type": "projection"}]}}]}}
        with open(os.path.join(tmp, "ctrecon.json"), "w") as f:
            json.dump(config, f)
        # As a service runs: no RUST_BACKTRACE (with it, every error a library makes walks the stack).
        env = {k: v for k, v in os.environ.items() if k not in ("RUST_BACKTRACE", "RUST_LIB_BACKTRACE")}
        env.update(CTRECON_LOG_FORMAT="json", RUST_LOG="warn")
        ctrecon = subprocess.Popen([binary, "serve", "--bind", f"127.0.0.1:{c_http}", "--config",
                                    os.path.join(tmp, "ctrecon.json")], env=env,
                                   stdout=subprocess.DEVNULL, stderr=open(os.path.join(tmp, "ctrecon.log"), "w"))
        procs.append(ctrecon)
        try:
            wait_http(c_http, "/healthz")
        except SystemExit:
            sys.stderr.write(open(os.path.join(tmp, "ctrecon.log")).read()[-2000:])
            raise
        wait_http(o_http, "/system")
        wait_port(scp_port)
        wait_port(c_dicom)

        # 1 + 2. Receive, interleaved rounds.
        idle_kb = proc_kb(ctrecon.pid, "VmRSS")
        times = {"ctrecon": [], "storescp": [], "Orthanc": []}
        t_start = time.time()
        for _ in range(args.rounds):
            times["ctrecon"].append(storescu(c_dicom, "CTRECON", src))
            times["storescp"].append(storescu(scp_port, "STORESCP", src))
            for study in http_json(o_http, "GET", "/studies")[1]:
                http_json(o_http, "DELETE", f"/studies/{study}")
            times["Orthanc"].append(storescu(o_dicom, "ORTHANC", src))
        hwm_kb = proc_kb(ctrecon.pid, "VmHWM")
        if time.time() - t_start > STABLE_AGE_SECS:
            print("warning: the rounds outlasted the stable age; the peak may include assembly")
        mb = sum(sizes) / 1e6
        print(f"\nreceive by C-STORE from storescu ({args.rounds} rounds)")
        print(f"{'receiver':10} {'median s':>9} {'best s':>8} {'MB/s':>7}")
        for name, ts in times.items():
            med = statistics.median(ts)
            print(f"{name:10} {med:9.2f} {min(ts):8.2f} {mb / med:7.1f}")
        fastest = min(statistics.median(t) for n, t in times.items() if n != "ctrecon")
        print(f"ctrecon / faster of the others: {statistics.median(times['ctrecon']) / fastest:.2f}x (goal: <= 1.5x)")
        inst_mb = max(sizes) / 1e6
        print(f"\nctrecon memory: {idle_kb / 1024:.1f} MB resident before, peak {hwm_kb / 1024:.1f} MB while receiving: "
              f"+{(hwm_kb - idle_kb) / 1024:.1f} MB, {(hwm_kb - idle_kb) / 1024 / inst_mb:.1f} x one instance "
              f"({inst_mb:.2f} MB; goal: under 2 x one instance plus a constant)")

        # 3. Send the derived series.
        def first_delivery():
            v = http_json(c_http, "GET", "/v1/deliveries?rule=bench")[1]
            d = v.get("deliveries", [])
            return d[0] if d and d[0]["state"] in ("succeeded", "failed") else None
        first = wait_until("the rule's delivery", first_delivery, 900, 0.5)
        if first["state"] != "succeeded":
            raise SystemExit(f"the rule's delivery failed: {first}")
        job = first["job_id"]
        for study in http_json(o_http, "GET", "/studies")[1]:
            http_json(o_http, "DELETE", f"/studies/{study}")
        c_to_o, d = delivery(c_http, job, "ORTHANC")
        n = sum(1 for i in d["instances"] if i["sop_class_uid"] == "1.2.840.10008.5.1.4.1.1.2")
        extra = len(d["instances"]) - n
        shutil.rmtree(scp_dir)
        os.makedirs(scp_dir)
        c_to_scp, _ = delivery(c_http, job, "STORESCP")
        derived = [s for s in http_json(o_http, "GET", "/series")[1]
                   if http_json(o_http, "GET", f"/series/{s}")[1]["MainDicomTags"].get("Modality") == "CT"]
        shutil.rmtree(scp_dir)
        os.makedirs(scp_dir)
        t0 = time.perf_counter()
        status, _ = http_json(o_http, "POST", "/modalities/STORESCP/store",
                              {"Resources": derived[:1], "Synchronous": True})
        o_to_scp = time.perf_counter() - t0
        got = os.listdir(scp_dir)
        derived_mb = sum(os.path.getsize(os.path.join(scp_dir, f)) for f in got) / 1e6
        print(f"\nsend the derived series ({n} CT instances, {derived_mb:.1f} MB as storescp wrote them; "
              f"ctrecon's deliveries also carry the rule's {extra} Secondary Capture)")
        print(f"{'from → to':22} {'seconds':>8}")
        print(f"{'ctrecon → Orthanc':22} {c_to_o:8.2f}")
        print(f"{'ctrecon → storescp':22} {c_to_scp:8.2f}")
        print(f"{'Orthanc → storescp':22} {o_to_scp:8.2f}  (HTTP {status}, {len(got)} files)")
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
