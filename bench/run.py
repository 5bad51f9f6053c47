"""Run the benchmarks: ``python -m bench.run [--quick] [names]``.

Imports every ``bench/bench_<name>.py`` (or only the ``names`` given, with or without the ``bench_``
prefix), calls its ``run(quick)``, merges the results into ``bench/results.json`` (results of
benchmarks not run this time are kept, as are those another run writes meanwhile; machine and date recorded
per benchmark) and writes the
summary tables to ``bench/results.md``.

A benchmark's ``"table"`` is a list of rows: dicts (columns = their keys, in first-seen order),
sequences (unnamed columns) or plain strings (listed as notes).
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib
import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path

from common.atomic import atomic_paths

HERE = Path(__file__).resolve().parent
RESULTS_JSON = HERE / "results.json"
RESULTS_MD = HERE / "results.md"


def available() -> list[str]:
    """Benchmark names (``bench_<name>.py`` in this folder), sorted."""
    return sorted(p.stem.removeprefix("bench_") for p in HERE.glob("bench_*.py"))


def machine() -> dict:
    """What the numbers were measured on."""
    import numpy as np

    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        mem_gib = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError):
        mem_gib = None
    return {
        "platform": platform.platform(),
        "cpu": cpu,
        "cpus": os.cpu_count(),
        "memory_gib": mem_gib,
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "load_average": [round(x, 1) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None,
    }


def _cell(v) -> str:
    if isinstance(v, bool):
        return "yes" if v else "**no**"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v).replace("|", "\\|")


def markdown(results: dict) -> str:
    """Summary tables of all benchmarks in ``results`` (the results.json layout)."""
    lines = ["# Benchmark results", "", "Written by `python -m bench.run`; details in `bench/results.json`.", ""]
    for name, entry in sorted(results.get("benchmarks", {}).items()):
        m = entry.get("machine", {})
        mode = "quick" if entry.get("quick") else "full"
        lines += [f"## {name}", "",
                  f"{entry.get('date', '?')}, {mode}, {entry.get('seconds', 0):.0f} s; "
                  f"{m.get('cpu', '?')} x{m.get('cpus', '?')}, load {m.get('load_average', '?')}", ""]
        if "error" in entry:
            lines += ["```", entry["error"].strip()[-1500:], "```", ""]
            continue
        rows = entry.get("result", {}).get("table", [])
        dict_rows = [r for r in rows if isinstance(r, dict)]
        seq_rows = [r for r in rows if isinstance(r, list | tuple)]
        notes = [r for r in rows if not isinstance(r, dict | list | tuple)]
        if dict_rows:
            cols = list(dict.fromkeys(k for r in dict_rows for k in r))
            lines += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
            lines += ["| " + " | ".join(_cell(r.get(c, "")) for c in cols) + " |" for r in dict_rows]
        if seq_rows:
            width = max(len(r) for r in seq_rows)
            lines += ["|" + " |" * width, "|" + "---|" * width]
            lines += ["| " + " | ".join(_cell(v) for v in r) + " |" for r in seq_rows]
        lines += [f"- {_cell(n)}" for n in notes]
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.run", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (each benchmark < 60 s)")
    parser.add_argument("names", nargs="*", help=f"benchmarks to run (default: all of {available()})")
    args = parser.parse_args(argv)
    names = [n.removeprefix("bench_") for n in args.names] or available()
    unknown = sorted(set(names) - set(available()))
    if unknown:
        parser.error(f"no benchmark {unknown}; have {available()}")

    failed = []
    info = machine()
    for name in names:
        print(f"== bench_{name} ({'quick' if args.quick else 'full'})", flush=True)
        entry = {"date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "quick": args.quick, "machine": info}
        t = time.perf_counter()
        try:
            module = importlib.import_module(f"bench.bench_{name}")
            entry["result"] = module.run(quick=args.quick)
            json.dumps(entry["result"])  # must be JSON-serialisable
        except Exception:
            entry.pop("result", None)
            entry["error"] = traceback.format_exc()
            failed.append(name)
            print(entry["error"], file=sys.stderr)
        entry["seconds"] = time.perf_counter() - t
        # read just before writing, so that a benchmark run in another process meanwhile keeps its entry
        results = json.loads(RESULTS_JSON.read_text()) if RESULTS_JSON.exists() else {}
        results.setdefault("benchmarks", {})[name] = entry
        results["updated"] = entry["date"]
        # write after each benchmark so a later failure or interrupt keeps the finished ones
        with atomic_paths(RESULTS_JSON, RESULTS_MD) as (tmp_json, tmp_md):
            tmp_json.write_text(json.dumps(results, indent=1) + "\n")
            tmp_md.write_text(markdown(results))
    print(markdown({"benchmarks": {n: results["benchmarks"][n] for n in names}}))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
