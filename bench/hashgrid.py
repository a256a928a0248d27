"""Hash-grid forward + backward time, eager against the compiled corner kernel.

Usage: ``OMP_WAIT_POLICY=PASSIVE python bench/hashgrid.py THREADS`` (compiled, the default; ``UAVSIM_COMPILE=0``:
eager). 32,768 points (1,024 rays x 32 samples), 2 features per level, levels growing 1.45x from
(8, 6, 3) cells; the first call (which compiles) is timed apart from the mean of the next 10.
"""

import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the repo's fields, not bench/fields.py
from fields.encodings import HashGrid, HashGridConfig  # noqa: E402


def grid(levels: int, log2_table: int) -> HashGrid:
    res = [(int(8 * 1.45**i), int(6 * 1.45**i), int(2 * 1.45**i) + 1) for i in range(levels)]
    return HashGrid(HashGridConfig(resolutions=res, features=2, log2_table=log2_table))


def main() -> None:
    torch.set_num_threads(int(sys.argv[1]) if len(sys.argv) > 1 else 1)
    x = torch.rand(32768, 3)
    for levels, log2 in [(14, 19), (7, 16)]:
        g = grid(levels, log2)

        def step(g=g):
            g.table.grad = None
            g(x).sum().backward()

        t0 = time.perf_counter()
        step()
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(10):
            step()
        print(f"levels {levels} table 2^{log2}: first call {first:.2f} s, "
              f"forward+backward {(time.perf_counter() - t0) / 10 * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
