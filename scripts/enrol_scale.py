"""Enrolment at a warehouse catalogue's size: time, disk, resumption, adding and removing products.

    python scripts/enrol_scale.py <gallery folder> [--ckpt pretrained] [--out enrol_scale.json] [--kill-after 20]

On a copy-free gallery folder (``<gallery>/<object>/<plane>.png``, e.g. ``<out>/n10000/gallery`` of
``python -m matl.unseen condition=catalog``), with the process's threads as given (``OMP_NUM_THREADS``):

1. ``fresh_s``: ``python -m matl.enrol`` from an empty cache (the folder's ``.matl_gallery_*`` removed first), in a
   subprocess, as a user runs it; ``s_per_1000_products`` from it; ``cache_bytes_per_product``: the cache's size.
2. ``resumed_s``: the cache emptied again, an enrolment killed (SIGTERM, as a job scheduler or ``kill`` stops it)
   after ``--kill-after`` seconds, then run again: the second run's time, and ``kept_products``: the products the
   killed run had written.
3. ``cached_s``: an enrolment that reads every product from the cache; ``grown_s``: the same after one product
   folder was added (a copy of the first under a new name; removed again at the end).
4. In one process (``Recognizer``): ``add_ms`` (``Recognizer.add`` of one plane) and the first query after it,
   ``remove_ms`` and the first query after it, ``query_ms``: the median of 20 single queries (files of the
   gallery's own planes), the gallery in memory.

Writes ``--out`` (JSON) and prints it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

from matl import Recognizer
from matl.utils.io import write_json


def enrol_command(gallery: Path, ckpt: str, run_dir: Path) -> list[str]:
    return [sys.executable, "-m", "matl.enrol", f"ckpt={ckpt}", f"gallery={gallery}", "threshold=null",
            f"hydra.run.dir={run_dir}"]


def clear_cache(gallery: Path) -> None:
    for folder in gallery.glob(".matl_gallery_*"):
        shutil.rmtree(folder) if folder.is_dir() else folder.unlink()


def cached_products(gallery: Path) -> int:
    return sum(1 for folder in gallery.glob(".matl_gallery_*") if folder.is_dir() for _ in folder.glob("*.pt"))


def timed_enrol(gallery: Path, ckpt: str, run_dir: Path) -> float:
    start = time.perf_counter()
    subprocess.run(enrol_command(gallery, ckpt, run_dir), check=True, capture_output=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("gallery", type=Path)
    parser.add_argument("--ckpt", default="pretrained")
    parser.add_argument("--out", type=Path, default=Path("enrol_scale.json"))
    parser.add_argument("--kill-after", type=float, default=20.0)
    args = parser.parse_args()
    gallery = args.gallery.resolve()
    products = sorted(p for p in gallery.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not products:
        sys.exit(f"error: {gallery} holds no product folders (<gallery>/<object>/<plane>.png)")
    runs = args.out.resolve().parent / f"{args.out.stem}_runs"
    result: dict[str, object] = {"gallery": str(gallery), "products": len(products),
                                 "threads": os.environ.get("OMP_NUM_THREADS")}

    clear_cache(gallery)
    result["fresh_s"] = timed_enrol(gallery, args.ckpt, runs / "fresh")
    result["s_per_1000_products"] = 1000.0 * float(result["fresh_s"]) / len(products)
    cache = [f for folder in gallery.glob(".matl_gallery_*") for f in folder.glob("*.pt")]
    result["cache_bytes_per_product"] = sum(f.stat().st_size for f in cache) / len(products)

    clear_cache(gallery)
    killed = subprocess.Popen(enrol_command(gallery, args.ckpt, runs / "killed"), stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    time.sleep(args.kill_after)
    killed.send_signal(signal.SIGTERM)
    killed.wait()
    result["kept_products"] = cached_products(gallery)
    result["resumed_s"] = timed_enrol(gallery, args.ckpt, runs / "resumed")

    result["cached_s"] = timed_enrol(gallery, args.ckpt, runs / "cached")
    extra = gallery / f"{products[0].name}__copy"
    shutil.copytree(products[0], extra)
    try:
        result["grown_s"] = timed_enrol(gallery, args.ckpt, runs / "grown")
    finally:
        shutil.rmtree(extra)

    rec = Recognizer.from_checkpoint(args.ckpt, threshold=None).enrol(gallery)
    plane = next(products[0].glob("*.png"), None) or next(products[0].iterdir())
    queries = [str(next(p.iterdir())) for p in products[1:21]]
    rec.predict(queries[0])
    start = time.perf_counter()
    rec.add("added_product", "front", str(plane))
    result["add_ms"] = 1000.0 * (time.perf_counter() - start)
    start = time.perf_counter()
    rec.predict(queries[1])
    result["first_query_after_add_ms"] = 1000.0 * (time.perf_counter() - start)
    start = time.perf_counter()
    rec.remove("added_product")
    result["remove_ms"] = 1000.0 * (time.perf_counter() - start)
    start = time.perf_counter()
    rec.predict(queries[2])
    result["first_query_after_remove_ms"] = 1000.0 * (time.perf_counter() - start)
    times = []
    for query in queries:
        start = time.perf_counter()
        rec.predict(query)
        times.append(1000.0 * (time.perf_counter() - start))
    result["query_ms"] = statistics.median(times)
    write_json(args.out, result)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
