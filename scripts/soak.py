"""Soak test: several Python threads share one Matcher and XFeat for a while, on inputs of
mixed sizes; every output must equal the first output of the same input, and the process's
resident memory must stay flat after warm-up.

    python scripts/soak.py --threads 4 --minutes 10 --out benches/results/soak.json
"""
from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

import numpy as np

import paraformer

ROOT = Path(__file__).resolve().parents[1]


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=4)
    ap.add_argument("--minutes", type=float, default=10)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()

    rng = np.random.default_rng(0)
    matchers = [paraformer.Matcher.pretrained(n) for n in paraformer.pretrained_names()]
    inputs = []
    for k0, k1 in ((64, 80), (512, 300), (1024, 1024), (2048, 1500), (1, 200), (0, 10)):
        f = []
        for k in (k0, k1):
            d = rng.normal(size=(k, 64)).astype(np.float32)
            f.append({"keypoints": rng.uniform(0, 600, (k, 2)).astype(np.float32),
                      "descriptors": d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-6),
                      "image_size": (640, 480)})
        inputs.append(tuple(f))
    images = [ROOT / "assets" / "sample" / "coffee_0.jpg", ROOT / "assets" / "sample" / "coffee_1.jpg"]

    def run_one(job: int):
        if job % 7 == 6:
            return ("extract", paraformer.extract(images[job % 2], max_keypoints=1024))
        m = matchers[job % len(matchers)]
        f0, f1 = inputs[job % len(inputs)]
        if job % 5 == 4:
            return ("many", m.match_many([(f0, f1), (f1, f0)], num_threads=2))
        return ("pair", m.match_dicts(f0, f1))

    def key(job: int) -> tuple:
        return (job % 7 == 6, job % 2 if job % 7 == 6 else job % len(matchers), job % len(inputs), job % 5 == 4)

    reference: dict = {}
    lock = threading.Lock()
    stats = {"calls": 0, "mismatches": 0, "errors": 0}
    stop = time.time() + 60 * a.minutes
    samples: list[tuple[float, float]] = []

    def same(x, y) -> bool:
        if isinstance(x, list):
            return all(same(p, q) for p, q in zip(x, y))
        return all(np.array_equal(x[k], y[k]) for k in x)

    def worker(tid: int) -> None:
        job = tid
        while time.time() < stop:
            try:
                _, out = run_one(job)
            except Exception:  # noqa: BLE001 - counted and reported
                with lock:
                    stats["errors"] += 1
                job += a.threads
                continue
            k = key(job)
            with lock:
                stats["calls"] += 1
                if k not in reference:
                    reference[k] = out
                elif not same(reference[k], out):
                    stats["mismatches"] += 1
            job += a.threads

    threads = [threading.Thread(target=worker, args=(t,)) for t in range(a.threads)]
    t0 = time.time()
    for t in threads:
        t.start()
    while any(t.is_alive() for t in threads):
        time.sleep(5)
        samples.append((time.time() - t0, rss_mb()))
    for t in threads:
        t.join()
    warm = [r for s, r in samples if s > 0.2 * 60 * a.minutes] or [r for _, r in samples]
    res = {"threads": a.threads, "minutes": a.minutes, **stats,
           "rss_mb_after_warmup": {"min": min(warm), "max": max(warm), "first": warm[0], "last": warm[-1]},
           "rss_mb_samples": [(round(s), round(r, 1)) for s, r in samples]}
    print(json.dumps({k: v for k, v in res.items() if k != "rss_mb_samples"}, indent=1))
    if a.out:
        a.out.write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
