"""A straightforward vectorised numpy implementation of the docs/simulator.md
simulator (paper parameters, D uniform in [0.75, 1.75], margin 4 px), used
only as the speed reference of `scanloc bench simulate`.

Prints `frames_per_second=<number>` as its last line.
"""
import argparse
import time

import numpy as np


def simulate(rng, n, h=24, w=25, a=0.07, dwell=2e-6, retrace=1.1e-3, sxy=0.21, sz=1.36,
             bkg=8.4, nqd=7.0, margin=4.0):
    d = rng.uniform(0.75, 1.75, size=n)
    x0 = rng.uniform(-0.5 + margin, w - 0.5 - margin, size=n)
    y0 = rng.uniform(-0.5 + margin, h - 0.5 - margin, size=n)
    # Step durations: dwell between pixels of a row, dwell + retrace at row starts.
    dt = np.full(h * w, dwell)
    dt[::w] += retrace
    dt[0] = 0.0
    sd = np.sqrt(2.0 * d[:, None] * dt[None, :])  # (n, h*w)
    steps = rng.standard_normal((3, n, h * w)) * sd[None]
    pos = np.cumsum(steps, axis=2)
    X = pos[0] + ((x0 + 0.5) * a)[:, None]
    Y = pos[1] + ((y0 + 0.5) * a)[:, None]
    Z = pos[2]
    rows, cols = np.divmod(np.arange(h * w), w)
    bx = (cols + 0.5) * a
    by = (rows + 0.5) * a
    r2 = (X - bx) ** 2 + (Y - by) ** 2
    lam = (nqd / (2 * np.pi * sxy**2) * np.exp(-r2 / (2 * sxy**2))
           / np.sqrt(2 * np.pi * sz**2) * np.exp(-Z**2 / (2 * sz**2)) + bkg)
    counts = rng.poisson(lam).astype(np.uint16).reshape(n, h, w)
    cx = X.mean(axis=1) / a - 0.5
    cy = Y.mean(axis=1) / a - 0.5
    return counts, cx, cy


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--chunk", type=int, default=2000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    simulate(rng, min(args.chunk, args.frames))  # warm-up
    start = time.perf_counter()
    done = 0
    while done < args.frames:
        n = min(args.chunk, args.frames - done)
        simulate(rng, n)
        done += n
    elapsed = time.perf_counter() - start
    print(f"frames_per_second={args.frames / elapsed:.1f}")


if __name__ == "__main__":
    main()
