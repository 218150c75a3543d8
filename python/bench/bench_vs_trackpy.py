"""scanloc's Python API against TrackPy 0.7 in the same process, and the
numbers issue 63 asks for: the speed ratio of locate (batch) and link, the
peak memory of a 512 × 512 × 1,000 uint16 stack, Ctrl-C latency.

    .venv/bin/python python/bench/bench_vs_trackpy.py [--frames N] [--skip-memory]

On a loaded machine the ratios move with the load: run it on an idle one
for numbers to quote (docs/python.md, "Speed").
"""

import argparse
import _thread
import resource
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pandas as pd
import trackpy

import scanloc

trackpy.quiet()


def best_of(repeats, call):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = call()
        times.append(time.perf_counter() - start)
    return min(times), result


def random_walks(seed, particles, frames, size, step=1.0, blink=0.05):
    rng = np.random.default_rng(seed)
    paths = rng.uniform(0, size, (particles, 2)) + np.cumsum(rng.normal(0, step, (frames, particles, 2)), axis=0)
    frame = np.repeat(np.arange(frames), particles)
    table = pd.DataFrame({"frame": frame, "x": paths[..., 0].ravel(), "y": paths[..., 1].ravel()})
    return table[rng.uniform(size=len(table)) > blink].reset_index(drop=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--skip-memory", action="store_true")
    args = parser.parse_args()

    m = scanloc.Microscope(height=128, width=128, brightness=40)
    frames, _ = scanloc.simulate_recording(args.frames, seed=3, microscope=m, qd_density=0.05, progress=False)
    ours_t, ours = best_of(3, lambda: scanloc.batch(frames, 7, minmass=30, progress=False))
    theirs_t, theirs = best_of(1, lambda: trackpy.batch(frames, 7, minmass=30))
    print(f"locate: {len(frames)} frames of 128 × 128, {len(ours)} features (TrackPy {len(theirs)}): "
          f"scanloc {ours_t:.3f} s, trackpy.batch {theirs_t:.3f} s: {theirs_t / ours_t:.0f}×")

    table = random_walks(38, 400, 200, 300.0)
    ours_t, linked = best_of(5, lambda: scanloc.link(table, 4.0, memory=2))
    theirs_t, tp_linked = best_of(1, lambda: trackpy.link(table, 4.0, memory=2))
    same = {frozenset(g.index) for _, g in linked.groupby("particle")} == {frozenset(g.index) for _, g in tp_linked.groupby("particle")}
    print(f"link: {len(table)} localisations in 200 frames: scanloc {ours_t:.4f} s, trackpy.link {theirs_t:.3f} s: "
          f"{theirs_t / ours_t:.0f}×; same trajectories: {same}")

    if not args.skip_memory:
        code = textwrap.dedent("""
            import resource, time, numpy as np, scanloc
            stack = np.random.default_rng(0).integers(0, 30, (1000, 512, 512), dtype=np.uint16)
            before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
            start = time.perf_counter()
            features = scanloc.locate(stack, 7, minmass=200, progress=False)
            seconds = time.perf_counter() - start
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
            print(f"{stack.nbytes} {before} {peak} {seconds} {len(features)}")
        """)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
        nbytes, before, peak, seconds, count = int(out[0]), int(out[1]), int(out[2]), float(out[3]), int(out[4])
        print(f"memory: 512 × 512 × 1000 uint16 ({nbytes / 2**20:.0f} MiB): peak RSS {peak / 2**20:.0f} MiB "
              f"= {peak / nbytes:.2f}× the input (before locate {before / 2**20:.0f} MiB; locate added "
              f"{(peak - before) / 2**20:.0f} MiB), {seconds:.1f} s, {count} features")

    stack = np.tile(np.random.default_rng(1).poisson(8, (10, 256, 256)).astype(np.uint16), (300, 1, 1))
    latencies = []
    for _ in range(3):
        pressed = {}

        def press():
            pressed["at"] = time.monotonic()
            _thread.interrupt_main()

        timer = threading.Timer(0.5, press)
        timer.start()
        try:
            scanloc.locate(stack, 7, progress=False)
        except KeyboardInterrupt:
            latencies.append(time.monotonic() - pressed["at"])
        finally:
            timer.cancel()
    print("Ctrl-C latency: " + ", ".join(f"{l * 1000:.0f} ms" for l in latencies))


if __name__ == "__main__":
    main()
