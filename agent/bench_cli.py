"""``uavsim bench NAME``: run the speed-against-error benchmark ``bench/NAME.py``.

Benchmarks live as scripts in the source tree's ``bench/`` folder (they are run by hand too);
this command finds that folder next to the installed packages (an editable/source install) or
under ``--bench-dir``.
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path


def _default_bench_dir() -> Path:
    return Path(__file__).resolve().parent.parent / "bench"


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="speed-against-error benchmarks (bench/NAME.py)")
    p.add_argument("name", help="benchmark name, e.g. 'render'; 'list' lists them")
    p.add_argument("--bench-dir", type=Path, default=None, help="folder holding the scripts")
    p.add_argument("rest", nargs="*", help="arguments passed to the benchmark (after --)")
    p.set_defaults(func=run)


def run(args) -> int:
    bench_dir = args.bench_dir or _default_bench_dir()
    if not bench_dir.is_dir():
        raise FileNotFoundError(f"benchmark folder {bench_dir} not found (use --bench-dir)")
    available = sorted(p.stem for p in bench_dir.glob("*.py") if not p.stem.startswith("_"))
    if args.name == "list":
        print("\n".join(available))
        return 0
    script = bench_dir / f"{args.name}.py"
    if not script.is_file():
        raise FileNotFoundError(f"no benchmark {args.name!r}; available: {', '.join(available)}")
    old_argv = sys.argv
    sys.argv = [str(script), *args.rest]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exc:
        return int(exc.code or 0)
    finally:
        sys.argv = old_argv
    return 0
