"""TrackPy 0.7 `link` on a localisation table, as the speed reference of
`scanloc bench link`. Times `tp.link` alone (the table is read first; the
best of --repeats runs, as scanloc's figure is), writes
the linked table with its index as column `row` to --out, and prints
`localisations_per_second=<number>` last.
"""
import argparse
import time

import pandas as pd
import trackpy as tp


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--input", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--search-range", type=float, required=True)
    parser.add_argument("--memory", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    tp.quiet()
    locs = pd.read_csv(args.input)
    tp.link(locs.head(200), args.search_range, memory=args.memory)  # warm-up
    elapsed = float("inf")
    for _ in range(max(args.repeats, 1)):
        start = time.perf_counter()
        tracks = tp.link(locs, args.search_range, memory=args.memory)
        elapsed = min(elapsed, time.perf_counter() - start)
    tracks.to_csv(args.out, index_label="row")
    print(f"localisations_per_second={len(locs) / elapsed:.1f}")


if __name__ == "__main__":
    main()
