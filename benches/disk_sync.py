#!/usr/bin/env python3
"""What making received instances durable costs on this disk: 133 writes of 0.5 MB (LIDC-IDRI-0001's
CT slices), as a DICOM receiver would store them, each way timed over `--rounds` rounds:

- no sync: a new file per instance, written and closed (what DCMTK's `storescp` does);
- file synced: a new file per instance, `fsync` before it is acknowledged;
- file and folder synced: as above, and the folder's `fsync` so that the new name survives a crash
  (what ctrecon's DICOM node does for every instance);
- one log, `fdatasync`: every instance appended to one open file, its data synced;
- one pre-written log, `fdatasync`: the same into a file written and synced beforehand, so that no
  block is allocated while receiving.

Run: `python3 benches/disk_sync.py [--dir DIR] [--rounds N]` (DIR on the disk to measure; default a
temporary folder under the current one).
"""

import argparse
import os
import shutil
import statistics
import tempfile
import time

COUNT, SIZE = 133, 524288


def timed(fn):
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", default=".")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    work = tempfile.mkdtemp(prefix="disk-sync-", dir=args.dir)
    data = os.urandom(SIZE)

    def files(sync_file, sync_folder):
        def run():
            for i in range(COUNT):
                fd = os.open(os.path.join(work, "i%d" % i), os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o644)
                os.write(fd, data)
                if sync_file:
                    os.fsync(fd)
                os.close(fd)
                if sync_folder:
                    dfd = os.open(work, os.O_RDONLY)
                    os.fsync(dfd)
                    os.close(dfd)
        return run

    def log(prewritten):
        path = os.path.join(work, "log")
        if prewritten:
            fd = os.open(path, os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o644)
            os.write(fd, bytes(COUNT * SIZE))
            os.fsync(fd)
            os.close(fd)

        def run():
            fd = os.open(path, os.O_CREAT | os.O_WRONLY | (0 if prewritten else os.O_TRUNC), 0o644)
            for i in range(COUNT):
                os.pwrite(fd, data, i * SIZE)
                os.fdatasync(fd)
            os.close(fd)
        return run

    ways = [("no sync", lambda: files(False, False)), ("file synced", lambda: files(True, False)),
            ("file and folder synced", lambda: files(True, True)), ("one log, fdatasync", lambda: log(False)),
            ("one pre-written log, fdatasync", lambda: log(True))]
    times = {name: [] for name, _ in ways}
    try:
        for _ in range(args.rounds):
            for name, make in ways:
                run = make()
                times[name].append(timed(run))
                for f in os.listdir(work):
                    os.unlink(os.path.join(work, f))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print("| %d instances of %d KiB | median s | per instance ms |" % (COUNT, SIZE // 1024))
    print("|---|---|---|")
    for name, _ in ways:
        m = statistics.median(times[name])
        print("| %s | %.3f | %.2f |" % (name, m, 1000 * m / COUNT))


if __name__ == "__main__":
    main()
