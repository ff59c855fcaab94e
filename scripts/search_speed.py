"""A single query's exact gallery search: torch's chunked product against the compiled pass (docs/speed.md).

    python scripts/search_speed.py [--threads 1] [--anchors 30000 100000 300000] [--queries 20] [--rounds 5]

Random unit embeddings of 128 dimensions (as ``matl.bench``'s gallery scaling); each query is a gallery entry
plus a little noise, so it has a true nearest neighbour. In one process the two paths alternate query by query
(:func:`matl.models.search.nearest`, what batches use, and :meth:`ExactSearch.search` with one query, the
compiled pass), so the machine's drift falls on both alike; they must return the same index. Prints the median
time of each per gallery size.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from matl.models.search import ExactSearch, nearest

DIM = 128


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1, help="torch's intra-op threads")
    parser.add_argument("--anchors", type=int, nargs="+", default=[30_000, 100_000, 300_000])
    parser.add_argument("--queries", type=int, default=20)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    generator = torch.Generator().manual_seed(0)
    for size in args.anchors:
        gallery = torch.nn.functional.normalize(torch.randn(size, DIM, generator=generator), dim=1)
        search = ExactSearch(gallery)
        rows = torch.randint(0, size, (args.queries,), generator=generator)
        queries = gallery[rows] + 0.03 * torch.randn(args.queries, DIM, generator=generator)
        chunked, compiled = [], []
        for _ in range(args.rounds):
            for query in queries.split(1):
                start = time.perf_counter()
                expected = nearest(query, search.features, search.chunk, search.sq_norms)[0]
                chunked.append(time.perf_counter() - start)
                start = time.perf_counter()
                index = search.search(query)[0]
                compiled.append(time.perf_counter() - start)
                if int(index) != int(expected):
                    raise SystemExit(f"the two paths disagree at {size} anchors: {int(index)} != {int(expected)}")
        before, after = statistics.median(chunked), statistics.median(compiled)
        print(f"{size:>9,} anchors, {args.threads} thread(s): torch chunked {1e3 * before:.2f} ms, "
              f"compiled pass {1e3 * after:.2f} ms ({before / after:.1f}x)")


if __name__ == "__main__":
    main()
